"""What every synthetic scene shares: camera models, rendered frames, options and the render loop.

A scene is a pure function of ``(options, index)``: ``render(index)`` draws frame ``index``
at ``time_s = index / fps`` and returns its images and ground truth, whatever frames were
rendered before. Everything random comes from generators seeded by ``(seed, purpose[, index])``.
"""

from __future__ import annotations

import math
import numbers
import typing
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol

import numpy as np
from pydantic import TypeAdapter, ValidationError

from services.geometry.camera import CameraModel
from services.synthetic.fixtures import Fixtures
from services.synthetic.imaging import finish

NOISE_PURPOSE = 1
"""``scene_rng`` purposes below 100 are reserved for this module; scenes number theirs from 100."""

Truth = list[tuple[str, str, np.ndarray]]
"""Ground-truth transforms of one camera's frame: ``(parent_frame, child_frame, T_parent_child (4, 4))``."""


@dataclass(frozen=True)
class SceneFrame:
    """Frame ``index`` of a scene.

    ``images``: camera name -> (H, W) uint8; ``truth``: camera name -> ground-truth transforms.
    """

    index: int
    time_s: float
    images: dict[str, np.ndarray]
    truth: dict[str, Truth]


class Scene(Protocol):
    @property
    def name(self) -> str: ...

    cameras: tuple[CameraModel, ...]

    def render(self, index: int) -> SceneFrame: ...

    def fixtures(self) -> Fixtures: ...


@dataclass(frozen=True)
class SceneOptions:
    """Options every scene takes; a scene's own options subclass this.

    seed: makes everything random in the scene (layout, texture, path, noise) reproducible.
    width, height: image size in pixels. fps: frames per second (sets ``time_s`` and so the
    path speed per frame). noise_std: gaussian image noise, grey levels. blur_px: gaussian
    blur sigma, pixels. exposure: gain applied to the rendered grey levels (saturating).
    """

    seed: int = 0
    width: int = 640
    height: int = 480
    fps: float = 30.0
    noise_std: float = 0.0
    blur_px: float = 0.0
    exposure: float = 1.0

    def __post_init__(self) -> None:
        self.check_int("seed", 0, 2**63 - 1)
        self.check_int("width", 64, 8192)
        self.check_int("height", 64, 8192)
        self.check_float("fps", 0.0, 10000.0, low_open=True)
        self.check_float("noise_std", 0.0, 255.0)
        self.check_float("blur_px", 0.0, 100.0)
        self.check_float("exposure", 0.0, 100.0, low_open=True)

    def check_int(self, name: str, low: int, high: int) -> None:
        """Require option ``name`` to be an integer in [low, high]."""
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= int(value) <= high:
            raise ValueError(f"option {name}={value!r}: must be an integer in [{low}, {high}]")
        object.__setattr__(self, name, int(value))

    def check_float(self, name: str, low: float, high: float, low_open: bool = False) -> None:
        """Require option ``name`` to be a real number in [low, high] (or (low, high] when ``low_open``)."""
        value = getattr(self, name)
        valid = not isinstance(value, bool) and isinstance(value, numbers.Real) and math.isfinite(value)
        if not valid or not (low < value if low_open else low <= value) or value > high:
            interval = f"{'(' if low_open else '['}{low}, {high}]"
            raise ValueError(f"option {name}={value!r}: must be a number in {interval}")
        object.__setattr__(self, name, float(value))

    def check_choice(self, name: str, choices: tuple[str, ...]) -> None:
        """Require option ``name`` to be one of the strings ``choices``."""
        value = getattr(self, name)
        if not (isinstance(value, str) and value in choices):
            raise ValueError(f"option {name}={value!r}: must be one of {', '.join(choices)}")

    def check_bool(self, name: str) -> None:
        """Require option ``name`` to be True or False."""
        value = getattr(self, name)
        if not isinstance(value, bool):
            raise ValueError(f"option {name}={value!r}: must be true or false")

    @classmethod
    def parse(cls, scene: str, options: Mapping[str, Any]) -> SceneOptions:
        """Options of ``scene`` from keyword values; ValueError names any unknown or invalid option."""
        valid = sorted(f.name for f in fields(cls))
        unknown = sorted(set(options) - set(valid))
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(unknown)} for scene {scene!r}; "
                             f"valid options: {', '.join(valid)}")
        return cls(**options)

    @classmethod
    def from_text(cls, name: str, text: str) -> object:
        """Option ``name`` given as text (``--scene-option noise_std=0.5``) converted by its declared type;
        a tuple, list or dict option is written as JSON (``ids=[1,2,3]``). An unknown name is left to ``parse``."""
        annotation = typing.get_type_hints(cls).get(name)
        if annotation is None or annotation is str:
            return text
        adapter: TypeAdapter[object] = TypeAdapter(annotation)
        try:
            if typing.get_origin(annotation) in (tuple, list, dict):
                return adapter.validate_json(text)
            return adapter.validate_strings(text)
        except ValidationError as exc:
            raise ValueError(f"option {name}={text!r}: {exc.errors()[0]['msg']}") from exc


def scene_rng(seed: int, *purpose: int) -> np.random.Generator:
    """A generator for one purpose of a scene (layout, a frame's noise, ...), independent of the others."""
    return np.random.default_rng([seed, *purpose])


def noise_seed(seed: int, index: int, camera_number: int) -> int:
    """A 31-bit seed for the image noise of one camera's frame."""
    return int(np.random.SeedSequence([seed, NOISE_PURPOSE, index, camera_number]).generate_state(1)[0] >> 1)


class SyntheticScene(ABC):
    """Base of the scenes: checks the index, times the frame, post-processes every image.

    Subclasses set ``name``, ``Options`` and ``cameras`` and implement ``draw``.
    """

    name: ClassVar[str]
    Options: ClassVar[type[SceneOptions]] = SceneOptions
    cameras: tuple[CameraModel, ...]

    def __init__(self, options: SceneOptions | None = None):
        options = self.Options() if options is None else options
        if not isinstance(options, self.Options):
            raise ValueError(f"scene {self.name!r} takes {self.Options.__name__}, not {type(options).__name__}")
        self.options = options

    def fixtures(self) -> Fixtures:
        """What a tracker must be told to track the scene (``services.synthetic.fixtures``); here its rig alone."""
        return Fixtures(self.name, self.cameras)

    def time_s(self, index: int) -> float:
        """Time of frame ``index`` in seconds."""
        return index / self.options.fps

    def render(self, index: int) -> SceneFrame:
        """Frame ``index`` (>= 0): every camera's post-processed image and ground truth."""
        if isinstance(index, bool) or not isinstance(index, numbers.Integral) or index < 0:
            raise ValueError(f"frame index must be an integer >= 0, got {index!r}")
        index = int(index)
        images, truth = self.draw(index)
        o = self.options
        finished = {camera: finish(image, o.exposure, o.blur_px, o.noise_std, noise_seed(o.seed, index, number))
                    for number, (camera, image) in enumerate(images.items())}
        return SceneFrame(index, self.time_s(index), finished, truth)

    @abstractmethod
    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        """Noise-free (H, W) uint8 images and the ground truth of frame ``index``, per camera (in camera order)."""
