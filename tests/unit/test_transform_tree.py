"""``TransformTree``: edges in the order they come, joined so that every frame keeps one parent and no cycle forms."""

from __future__ import annotations

from services.geometry.transform_tree import TransformTree, TreeEdge


def test_new_children_are_kept_as_they_are_and_repeats_stay_put():
    tree = TransformTree()
    assert tree.edge("world", "rig") == TreeEdge("world", "rig", False)
    assert tree.edge("rig", "cam0") == TreeEdge("rig", "cam0", False)
    assert tree.edge("rig", "cam0") == TreeEdge("rig", "cam0", False)
    assert (tree.parent("cam0"), tree.root("cam0"), tree.parent("world")) == ("rig", "world", None)


def test_a_second_parent_that_is_a_root_is_hung_under_the_child_turned_round():
    tree = TransformTree()
    tree.edge("rig", "cam0")
    assert tree.edge("map", "cam0") == TreeEdge("cam0", "map", True)
    assert tree.edge("map", "cam0") == TreeEdge("cam0", "map", True)
    assert (tree.parent("map"), tree.root("map")) == ("cam0", "rig")


def test_an_edge_that_cannot_be_turned_round_gets_a_child_of_its_own():
    tree = TransformTree()
    tree.edge("rig", "cam0")
    tree.edge("rig", "cam1")
    tree.edge("cam0", "marker/3")
    assert tree.edge("cam1", "marker/3") == TreeEdge("cam1", "cam1/marker/3", False)
    assert tree.parent("marker/3") == "cam0"


def test_an_edge_that_would_close_a_cycle_is_not_turned_round():
    tree = TransformTree()
    tree.edge("world", "rig")
    tree.edge("rig", "cam0")
    assert tree.edge("world", "cam0") == TreeEdge("world", "world/cam0", False)
    assert tree.edge("cam0", "world") == TreeEdge("cam0", "cam0/world", False)
    assert tree.root("cam0") == "world"
