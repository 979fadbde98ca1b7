"""Pose estimation, one package per tracker: ``markers`` (planar markers and marker maps), ``bodies`` (rigid
bodies of IR spheres seen by a rig) and ``targets`` (natural-feature image targets); algorithms and their nodes.
``motion``, ``pose_filter`` and ``overlay`` serve more than one tracker."""
