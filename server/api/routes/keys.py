"""API keys (admin): create (the key is in this answer only), list, revoke; and any key's
own record (``GET /v1/keys/me``: what the console shows and offers)."""

from __future__ import annotations

from fastapi import APIRouter, status

from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import AdminKey, ReadKey, SessionDep, StateDep
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import KeyId
from monoloc.server.api.schemas_admin import KeyCreate, KeyCreated, KeyList, KeyPublic
from monoloc.server.storage import keys as keys_repo

router = APIRouter(prefix="/v1/keys", tags=["keys"], route_class=GuardedRoute)


@router.post(
    "",
    response_model=KeyCreated,
    status_code=status.HTTP_201_CREATED,
    responses={**AUTH_ERRORS, **error_responses(422)},
    summary="Create an API key",
)
def create_key(body: KeyCreate, session: SessionDep, _key: AdminKey) -> KeyCreated:
    """Only a hash is stored: copy ``key`` from this answer, it is not shown again.
    ``maps`` limits the key to those maps (422 if one does not exist, or with ``admin``)."""
    record, plaintext = keys_repo.create_api_key(session, body.name, body.scopes, body.maps)
    session.commit()
    return KeyCreated(**KeyPublic.model_validate(record).model_dump(), key=plaintext)


@router.get(
    "/me", response_model=KeyPublic, responses=AUTH_ERRORS, summary="The presented key's record"
)
def my_key(key: ReadKey) -> KeyPublic:
    """Name, prefix and scopes of the key this request presents (any valid key)."""
    return KeyPublic.model_validate(key)


@router.get("", response_model=KeyList, responses=AUTH_ERRORS, summary="List API keys")
def list_keys(session: SessionDep, _key: AdminKey, include_revoked: bool = True) -> KeyList:
    keys = keys_repo.list_api_keys(session, include_revoked=include_revoked)
    return KeyList(items=[KeyPublic.model_validate(k) for k in keys])


@router.delete(
    "/{key_id}",
    response_model=KeyPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 409)},
    summary="Revoke an API key",
)
def revoke_key(key_id: KeyId, session: SessionDep, state: StateDep, _key: AdminKey) -> KeyPublic:
    """Takes effect at once on this replica and within `MONOLOC_KEY_CACHE_S` (2 s by
    default: how long a replica trusts a key it has verified) on the others. Revoking a
    revoked key changes nothing. The last active admin key cannot be revoked (409)."""
    record = keys_repo.revoke_api_key(session, key_id)
    session.commit()
    state.keys.forget(key_id)
    return KeyPublic.model_validate(record)
