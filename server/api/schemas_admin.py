"""Request and response bodies of the key administration and health routes (pydantic v2),
each with an OpenAPI example; the conventions of server/api/schemas.py."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, Field, field_validator

from monoloc.server.api.openapi_rules import ADMIN_KEY_ALL_MAPS, rules_extra
from monoloc.server.api.params import DB_ID_MAX
from monoloc.server.api.schemas import (
    TIME_EXAMPLE,
    JsonInt,
    example,
    record_example,
    strict_example,
)
from monoloc.server.storage.keys import SCOPES

Scope = Literal["localize", "map:write", "metrics", "admin"]
assert set(SCOPES) == {"localize", "map:write", "metrics", "admin"}


class KeyCreate(BaseModel):
    model_config = strict_example(rules_extra(ADMIN_KEY_ALL_MAPS), name="car1", scopes=["localize"])
    name: str = Field(
        min_length=1,
        max_length=128,
        pattern=r"\S",
        description="1-128 characters, not only spaces (stored without surrounding spaces).",
    )
    scopes: list[Scope] = Field(min_length=1)
    maps: list[Annotated[JsonInt, Field(ge=1, le=DB_ID_MAX)]] | None = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="Limit the key to these maps (ids of existing maps): every other map "
        "is refused with 403, and lists show only these. Left out: every map. Not allowed "
        "with the admin scope (an admin key sees every map).",
    )


_KEY_EXAMPLE = dict(
    id=2,
    name="car1",
    prefix="mlk_3kq9XaB1",
    scopes=["localize"],
    created_at=TIME_EXAMPLE,
    revoked_at=None,
    maps=None,
)


class KeyPublic(BaseModel):
    model_config = record_example(**_KEY_EXAMPLE)
    id: int
    name: str
    prefix: str
    scopes: list[str]
    created_at: datetime
    revoked_at: datetime | None
    maps: list[int] | None = Field(description="The maps the key may touch; null: every map.")

    @field_validator("scopes", mode="before")
    @classmethod
    def _sorted(cls, scopes: Iterable[str]) -> list[str]:
        return sorted(scopes)  # a record holds them as a set

    @field_validator("maps", mode="before")
    @classmethod
    def _sorted_maps(cls, maps: Iterable[int] | None) -> list[int] | None:
        return None if maps is None else sorted(maps)


class KeyCreated(KeyPublic):
    model_config = example(**_KEY_EXAMPLE, key="mlk_3kq9XaB1Jm0c0lH9bXgk2s7QJX1FyFQw8mN5tq8aEo4")
    key: str = Field(description="The key itself; shown only in this answer.")


class KeyList(BaseModel):
    model_config = example(items=[_KEY_EXAMPLE])
    items: list[KeyPublic]


class HealthStatus(BaseModel):
    model_config = example(status="ok", maps_loaded=2)
    status: str
    maps_loaded: int | None = None
