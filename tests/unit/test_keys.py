"""Key expressions: the layout every process agrees on, and the names it refuses."""

from __future__ import annotations

import re

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.keys import Keys, check_name

names = st.from_regex(r"[A-Za-z0-9_.\-]{1,12}", fullmatch=True)

LAYOUT = [
    (lambda k: k.image("cam0"), "ar/rig0/cam0/image"),
    (lambda k: k.camera_info("cam0"), "ar/rig0/cam0/camera_info"),
    (lambda k: k.calibration("cam0"), "ar/rig0/cam0/calibration"),
    (lambda k: k.truth("cam0"), "ar/rig0/cam0/truth"),
    (lambda k: k.markers("cam0"), "ar/rig0/cam0/markers"),
    (lambda k: k.blobs("cam0"), "ar/rig0/cam0/blobs"),
    (lambda k: k.keypoints("cam0"), "ar/rig0/cam0/keypoints"),
    (lambda k: k.echo("cam0"), "ar/rig0/cam0/echo"),
    (lambda k: k.overlay("cam0"), "ar/rig0/cam0/overlay"),
    (lambda k: k.keyframes("cam0"), "ar/rig0/cam0/keyframes"),
    (lambda k: k.camera_map("cam0"), "ar/rig0/cam0/map"),
    (lambda k: k.timings("cam0"), "ar/rig0/cam0/timings"),
    (lambda k: k.slam_pose("cam0"), "ar/rig0/pose/slam/cam0"),
    (lambda k: k.pose("marker-7"), "ar/rig0/pose/marker-7"),
    (lambda k: k.pose("body/wand"), "ar/rig0/pose/body/wand"),
    (lambda k: k.poses(), "ar/rig0/pose/**"),
    (lambda k: k.bodies(), "ar/rig0/bodies"),
    (lambda k: k.map(), "ar/rig0/map"),
    (lambda k: k.static_transforms("cap"), "ar/rig0/tf_static/cap"),
    (lambda k: k.rig_static_transforms(), "ar/rig0/tf_static/*"),
    (lambda k: k.all_static_transforms(), "ar/*/tf_static/*"),
    (lambda k: k.node("detect_0"), "ar/rig0/node/detect_0"),
    (lambda k: k.stats("detect_0"), "ar/rig0/node/detect_0/stats"),
    (lambda k: k.state("detect_0"), "ar/rig0/node/detect_0/state"),
    (lambda k: k.errors("detect_0"), "ar/rig0/node/detect_0/errors"),
    (lambda k: k.everything(), "ar/rig0/**"),
    (lambda k: k.all_nodes(), "ar/*/node/*"),
    (lambda k: k.all_states(), "ar/*/node/*/state"),
    (lambda k: k.all_stats(), "ar/*/node/*/stats"),
]


@pytest.mark.parametrize(("build", "expected"), LAYOUT, ids=[key for _, key in LAYOUT])
def test_default_layout(build, expected: str):
    assert build(Keys()) == expected


def test_namespace_may_hold_several_segments():
    keys = Keys(namespace="site/lab1", rig="stereo.A")
    assert keys.prefix == "site/lab1/stereo.A"
    assert keys.image("left") == "site/lab1/stereo.A/left/image"
    assert keys.all_nodes() == "site/lab1/*/node/*"


BAD_NAMES = ["", "a/b", "*", "**", "cam*", "$*", "a$b", "a b", "a?b", "a#b", "ü", "cam\n"]
BAD_SEGMENTS = ["", "/", "a/", "/a", "a//b", "a/*", "a/**/b", "a/$x", "a b/c"]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_invalid_single_names_are_refused(name: str):
    keys = Keys()
    for build, what in [(keys.image, "camera"), (keys.node, "node name"), (lambda n: Keys(rig=n), "rig")]:
        with pytest.raises(ValueError, match=f"{what} .* is not a valid key name") as caught:
            build(name)
        assert repr(name) in str(caught.value)


@pytest.mark.parametrize("name", BAD_SEGMENTS + [n for n in BAD_NAMES if n != "a/b"])
def test_invalid_segmented_names_are_refused(name: str):
    with pytest.raises(ValueError, match="namespace .* is not a valid key name"):
        Keys(namespace=name)
    with pytest.raises(ValueError, match="target .* is not a valid key name"):
        Keys().pose(name)


def test_error_says_what_is_allowed():
    with pytest.raises(ValueError, match="use letters, digits, '_', '-', '.' and '/' between segments"):
        check_name("a//b", "namespace", segments=True)


@settings(max_examples=200, deadline=None)
@given(st.text(min_size=1, max_size=12).filter(lambda s: any(not (c.isascii() and (c.isalnum() or c in "_.-"))
                                                             for c in s)))
def test_any_name_with_a_character_outside_the_set_is_refused(name: str):
    with pytest.raises(ValueError):
        check_name(name, "name")


@settings(max_examples=200, deadline=None)
@given(namespace=st.lists(names, min_size=1, max_size=3).map("/".join), rig=names, node=names)
def test_split_node_inverts_node_keys(namespace: str, rig: str, node: str):
    keys = Keys(namespace=namespace, rig=rig)
    for key in (keys.node(node), keys.stats(node), keys.state(node), keys.errors(node)):
        assert keys.split_node(key) == (rig, node)


def test_split_node_reads_other_rigs_of_the_namespace():
    assert Keys().split_node("ar/rig7/node/tracker/stats") == ("rig7", "tracker")


NOT_NODE_KEYS = ["ar/rig0/cam0/image", "ar/rig0/node", "other/rig0/node/x", "arx/rig0/node/x", "ar", "",
                 "rig0/node/x"]


@pytest.mark.parametrize("key", NOT_NODE_KEYS)
def test_split_node_refuses_other_keys(key: str):
    with pytest.raises(ValueError, match="is not a node key under 'ar'"):
        Keys().split_node(key)


RESOLVED = [
    ("cam0/image", "ar/rig0/cam0/image"),
    ("pose/**", "ar/rig0/pose/**"),
    ("*/markers", "ar/rig0/*/markers"),
    ("cam$*/image", "ar/rig0/cam$*/image"),
    ("ar/rig1/cam0/image", "ar/rig1/cam0/image"),
    ("ar/*/node/*/stats", "ar/*/node/*/stats"),
    ("ar", "ar/rig0/ar"),
    ("arx/y", "ar/rig0/arx/y"),
]


@pytest.mark.parametrize(("given_key", "expected"), RESOLVED)
def test_resolve_is_relative_to_the_rig_unless_the_key_starts_with_the_namespace(given_key: str, expected: str):
    assert Keys().resolve(given_key) == expected


def test_resolve_under_a_namespace_of_several_segments():
    keys = Keys(namespace="site/lab1", rig="r")
    assert keys.resolve("site/lab1/r2/cam0/image") == "site/lab1/r2/cam0/image"
    assert keys.resolve("site/cam0") == "site/lab1/r/site/cam0"


BAD_EXPRESSIONS = [
    ("a b//c", "empty segment"),
    ("", "it is empty"),
    ("/cam0/image", "empty segment"),
    ("cam0/image/", "empty segment"),
    ("a b/c", "segment 'a b'"),
    ("cam0/image?x=1", "segment 'image?x=1'"),
    ("cam*/image", "segment 'cam*'"),
    ("$*/image", "segment '$*'"),
    ("pose/**/**", "write '**' for '**/**'"),
    ("**/*", "write '*/**' for '**/*'"),
]


@pytest.mark.parametrize(("given_key", "why"), BAD_EXPRESSIONS)
def test_resolve_refuses_a_bad_expression_naming_it_and_why(given_key: str, why: str):
    expected = f"key expression {re.escape(repr(given_key))} is not valid: .*{re.escape(why)}"
    with pytest.raises(ValueError, match=expected):
        Keys().resolve(given_key)


segments = st.sampled_from(["cam0", "*", "**", "a b", "", "x$*", "$*", "$*$*", "a?", "é", "a.b-c_d", "#"])


@settings(max_examples=300, deadline=None)
@given(st.lists(segments, min_size=1, max_size=4).map("/".join))
def test_every_expression_resolve_accepts_is_one_zenoh_accepts_unchanged(expression: str):
    try:
        resolved = Keys().resolve(expression)
    except ValueError:
        return
    assert str(zenoh.KeyExpr(resolved)) == resolved


@pytest.mark.parametrize("given_key", [key for key, _ in BAD_EXPRESSIONS if key != "a b/c"])
def test_the_bad_expressions_are_bad_for_zenoh_too(given_key: str):
    """(Zenoh takes spaces inside a segment; artrack's names never hold one.)"""
    with pytest.raises(zenoh.ZError):
        zenoh.KeyExpr(f"ar/rig0/{given_key}" if given_key else given_key)
