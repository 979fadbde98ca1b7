"""The marker detector's options, shared by every node that detects markers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from services.detection.markers.detector import DEFAULT_REFINEMENT, MarkerDetector

DEFAULT_DICTIONARY = "DICT_4X4_50"


class DetectorSettings(BaseModel):
    """Which markers to look for and how (see ``MarkerDetector``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    TUNING: ClassVar[frozenset[str]] = frozenset({"marker_length", "lengths", "refinement", "parameters"})
    """The fields a running detector may take new values of (all but the dictionary)."""

    dictionary: str = Field(default=DEFAULT_DICTIONARY,
                            description="cv2.aruco predefined dictionary name, or the path of a dictionary YAML")
    marker_length: float | None = Field(default=None, gt=0.0, allow_inf_nan=False,
                                        description="side of a marker's black square, metres (> 0); default: "
                                        "unknown (a synthetic scene's own, with artrack run)")
    lengths: dict[int, Annotated[float, Field(gt=0.0, allow_inf_nan=False)]] = Field(
        default_factory=dict, description="side lengths of single ids, metres (> 0)")
    refinement: Literal["lines", "none", "subpix", "contour", "apriltag"] = Field(
        default=DEFAULT_REFINEMENT, description="corner refinement: lines (subpix, then lines fitted to each side), "
        "or OpenCV's none, subpix, contour, apriltag")
    parameters: dict[str, Any] = Field(default_factory=dict,
                                       description="cv2.aruco.DetectorParameters fields to override, by name")

    def tuning(self) -> dict[str, Any]:
        """The ``TUNING`` fields' values."""
        return {name: getattr(self, name) for name in sorted(self.TUNING)}

    def dictionary_name(self, fallback: str | None = None) -> str:
        """The dictionary given, else ``fallback`` (a board's), else the default."""
        return self.dictionary if "dictionary" in self.model_fields_set or not fallback else fallback

    def detector(self, dictionary: str | None = None, lengths: Mapping[int, float] | None = None) -> MarkerDetector:
        """The detector these settings describe. ``dictionary`` stands in for the default one when no
        dictionary was given; ``lengths`` are side lengths known elsewhere (a board), which ``lengths``
        given here override. Raises ValueError naming a bad dictionary, refinement or parameter."""
        return MarkerDetector(self.dictionary_name(dictionary), marker_length=self.marker_length or 0.0,
                              lengths={**(lengths or {}), **self.lengths}, refinement=self.refinement,
                              parameters=self.parameters)
