"""The slam node's anchor marker parameters, without a bus: refused without a side, its output key only when on."""

from __future__ import annotations

import pytest

from services.slam.node import KIND, Params


def test_an_anchor_marker_needs_its_side_and_a_known_dictionary():
    with pytest.raises(ValueError, match="anchor_marker needs the marker's side: marker_length"):
        KIND.preflight(Params(anchor_marker=3))
    with pytest.raises(ValueError, match="DICT_9X9_1"):
        KIND.preflight(Params(anchor_marker=3, marker_length=0.2, dictionary="DICT_9X9_1"))
    KIND.preflight(Params(anchor_marker=3, marker_length=0.2))


def test_the_anchored_pose_is_an_output_only_with_an_anchor_marker():
    assert "pose/slam/cam0/anchored" not in KIND.keys(Params())[1]
    assert "pose/slam/cam0/anchored" in KIND.keys(Params(anchor_marker=0, marker_length=0.3))[1]
