"""Textures: what a texture is (a :class:`TextureSpec`), its pixels (:class:`TextureLayers`),
and the :class:`TextureBank` that makes them on demand and keeps them in a bounded cache.

A bank knows no scenario: it is given a registry ``kind -> generator``. Each scenario
owns its registry (``monoloc.sim.urban.textures``, ``monoloc.sim.indoor.textures``); a
generator is a pure function ``(spec, rng) -> TextureLayers``, called with
``np.random.default_rng(spec.seed)``, so a texture depends only on its spec and not on
the order in which textures are first used.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class TextureSpec:
    """How to make one texture: generator kind (a key of a bank's registry), size, seed,
    params.

    ``params`` is a tuple of (name, value) pairs so the spec stays hashable.
    ``wrap``: the texture tiles beyond its edges (ground materials); otherwise its edge
    pixels repeat.
    """

    kind: str
    width_px: int
    height_px: int
    seed: int
    params: tuple = ()
    wrap: bool = False

    def param(self, name: str, default=None):
        for key, value in self.params:
            if key == name:
                return value
        return default


@dataclass(frozen=True)
class TextureLayers:
    """Generated pixels of one texture, each (H, W) uint8: albedo, and optional night
    emission (lit windows, lamps) and alpha (255 opaque, 0 transparent)."""

    albedo: np.ndarray
    emission: np.ndarray | None = None
    alpha: np.ndarray | None = None


TextureGenerator = Callable[[TextureSpec, np.random.Generator], TextureLayers]


def texture_seed(rng: np.random.Generator) -> int:
    """A texture's own seed, drawn from the scene's generator."""
    return int(rng.integers(0, 2**31))


def generate_texture(
    generators: Mapping[str, TextureGenerator], spec: TextureSpec
) -> TextureLayers:
    """Pixels of ``spec`` made by ``generators[spec.kind]`` (deterministic in ``spec.seed``)."""
    generator = generators.get(spec.kind)
    if generator is None:
        raise InvalidInputError(f"unknown texture kind {spec.kind!r}")
    return generator(spec, np.random.default_rng(spec.seed))


class TextureBank:
    """Lazily generated texture pyramids with a memory bound (least recently used out).

    ``get(spec, level, night)`` returns an (H, W, C) uint8 array whose channels are
    albedo, then emission (only if ``night`` and the texture has one), then alpha (if it
    has one), at pyramid level ``level`` (each level halves the size). ``generators``
    maps each texture kind the bank can make to its generator.
    """

    def __init__(
        self, generators: Mapping[str, TextureGenerator], max_bytes: int = 1_500_000_000
    ) -> None:
        self.generators = generators
        self.max_bytes = max_bytes
        self._layers: OrderedDict[TextureSpec, TextureLayers] = OrderedDict()
        self._levels: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._bytes = 0

    def layers(self, spec: TextureSpec) -> TextureLayers:
        if spec in self._layers:
            self._layers.move_to_end(spec)
            return self._layers[spec]
        layers = generate_texture(self.generators, spec)
        self._layers[spec] = layers
        self._account(
            sum(a.nbytes for a in (layers.albedo, layers.emission, layers.alpha) if a is not None)
        )
        return layers

    def get(self, spec: TextureSpec, level: int, night: bool = False) -> np.ndarray:
        key = (spec, level, night)
        if key in self._levels:
            self._levels.move_to_end(key)
            return self._levels[key]
        if level == 0:
            layers = self.layers(spec)
            channels = [layers.albedo]
            if night and layers.emission is not None:
                channels.append(layers.emission)
            if layers.alpha is not None:
                channels.append(layers.alpha)
            image = np.dstack(channels) if len(channels) > 1 else channels[0][:, :, None]
        else:
            import cv2

            finer = self.get(spec, level - 1, night)
            border = cv2.BORDER_WRAP if spec.wrap else cv2.BORDER_REFLECT_101
            if min(finer.shape[:2]) < 2:
                image = finer
            else:
                image = cv2.pyrDown(
                    finer, borderType=border if not spec.wrap else cv2.BORDER_REFLECT_101
                )
                if image.ndim == 2:
                    image = image[:, :, None]
        self._levels[key] = image
        self._account(image.nbytes)
        return image

    def _account(self, nbytes: int) -> None:
        self._bytes += nbytes
        while self._bytes > self.max_bytes and (len(self._levels) > 1 or len(self._layers) > 1):
            if self._levels:
                _, arr = self._levels.popitem(last=False)
                self._bytes -= arr.nbytes
            else:
                _, layers = self._layers.popitem(last=False)
                self._bytes -= sum(
                    a.nbytes
                    for a in (layers.albedo, layers.emission, layers.alpha)
                    if a is not None
                )
