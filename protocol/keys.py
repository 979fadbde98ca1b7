"""Key expressions: the one place where artrack's Zenoh key strings are built.

Layout, for namespace ``ar`` and rig ``rig0``::

    ar/rig0/<camera>/image            Image            frames of one camera
    ar/rig0/<camera>/camera_info      CameraInfo       its calibration, published with frames
    ar/rig0/<camera>/calibration      (queryable)      the same, on request
    ar/rig0/<camera>/truth            GroundTruth      exact poses of synthetic / mocap sources
    ar/rig0/<camera>/{markers,blobs,keypoints}         detections in that camera's images
    ar/rig0/<camera>/echo             Image            frames relayed by the echo node
    ar/rig0/<camera>/overlay          Image            frames with the tracked targets drawn (AR overlay)
    ar/rig0/<camera>/keyframes        Keyframes        the keyframe poses of the camera's SLAM map
    ar/rig0/<camera>/map              PointCloud       the points of the camera's SLAM map
    ar/rig0/<camera>/timings          StageTimings     how long each stage of a frame took (SLAM)
    ar/rig0/<camera>/targets          ImageTargets     the image targets a features node poses in the camera's
                                                       frames (size, corners in the target frame), published
                                                       before its first poses and answered on a queryable
    ar/rig0/pose/<target>             Pose             one tracked target (may span segments)
    ar/rig0/pose/slam/<camera>        Pose             SLAM: the camera in its map, ``T_map_camera``
    ar/rig0/bodies                    RigidBodies      all rigid bodies of the rig
    ar/rig0/map                       PointCloud       SLAM / triangulated points
    ar/rig0/points                    Points3D         a rig's triangulated sphere centres, with their bodies
    ar/rig0/tf_static/<node>          StaticTransforms the rig's static transforms one node holds (cameras'
                                      T_rig_camera), published once and answered on a queryable
    ar/rig0/node/<name>               (liveliness)     present while the node runs
    ar/rig0/node/<name>/stats         NodeStats        published every stats period
    ar/rig0/node/<name>/state         (queryable)      NodeStats on request
    ar/rig0/node/<name>/errors        ErrorReport      what the node skipped and why
    ar/rig0/node/<name>/control       (queryable)      ReplayControl -> ReplayStatus: replay's pause / resume / step
    ar/rig0/node/<name>/config        (queryable)      ConfigChange -> ConfigAnswer: live parameter changes
    ar/rig0/supervisor/<pipeline>     (queryable)      PipelineHealth of an ``artrack up`` process
    ar/rig0/client/<id>               (liveliness)     present while a client app is connected
    ar/rig0/client/<id>/state         (queryable)      ClientState: what the app subscribed to

Static data (``tf_static/<node>``, ``<camera>/targets``) is published once and answered on a queryable
at the same key; a subscriber that may come after the publication asks for it (``Keys.latched``).

The namespace may hold several segments (``site/lab1``); names are made of letters,
digits, ``_``, ``-`` and ``.``. Key expressions a user gives (``artrack echo``, ``record``,
``replay``) go through ``Keys.resolve``: relative to the rig prefix unless they start with
the namespace, and checked by ``check_expression``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated

from pydantic import AfterValidator

_NAME = re.compile(r"[A-Za-z0-9_.\-]+")


def check_name(value: str, what: str, *, segments: bool = False) -> str:
    """Return ``value`` if it is a valid key segment (or ``/``-joined segments); raise ValueError."""
    parts = value.split("/") if segments else [value]
    if not value or not all(_NAME.fullmatch(p) for p in parts):
        allowed = "letters, digits, '_', '-', '.'" + (" and '/' between segments" if segments else "")
        raise ValueError(f"{what} {value!r} is not a valid key name (use {allowed})")
    return value


_WILD_NAME = re.compile(r"(?:[A-Za-z0-9_.\-]|\$\*)+")
_NOT_CANONICAL = {"**/**": "**", "**/*": "*/**"}


def check_expression(value: str) -> str:
    """Return ``value`` if it is a key expression artrack can subscribe to; raise ValueError naming
    it and why. Segments are key names, ``*`` (one segment), ``**`` (any number of them), or names
    with ``$*`` inside (any characters within the segment), in Zenoh's canonical form."""
    def bad(why: str) -> ValueError:
        return ValueError(f"key expression {value!r} is not valid: {why}")

    if not value:
        raise bad("it is empty")
    chunks = value.split("/")
    if "" in chunks:
        raise bad("it has an empty segment (a leading, trailing or doubled '/')")
    for chunk in chunks:
        if chunk not in ("*", "**") and (chunk == "$*" or "$*$*" in chunk or not _WILD_NAME.fullmatch(chunk)):
            raise bad(f"segment {chunk!r} (use letters, digits, '_', '-', '.'; '*' or '**' as a whole segment, "
                      "'$*' inside one)")
    for pair, canon in _NOT_CANONICAL.items():
        if f"/{pair}/" in f"/{value}/":
            raise bad(f"write {canon!r} for {pair!r}")
    return value


KeyName = Annotated[str, AfterValidator(lambda value: check_name(value, "name"))]
"""A str field that must be one valid key segment (camera, node, rig names)."""


@dataclass(frozen=True)
class Keys:
    """Key expressions of one rig under one namespace."""

    namespace: str = "ar"
    rig: str = "rig0"

    def __post_init__(self) -> None:
        check_name(self.namespace, "namespace", segments=True)
        check_name(self.rig, "rig")

    @property
    def prefix(self) -> str:
        return f"{self.namespace}/{self.rig}"

    def resolve(self, key: str) -> str:
        """A key expression given by a user: as it is when it starts with the namespace, else
        relative to the rig prefix (``cam0/image`` -> ``ar/rig0/cam0/image``); ValueError naming
        it and why when it is not a valid expression (see ``check_expression``)."""
        check_expression(key)
        return key if key.startswith(self.namespace + "/") else f"{self.prefix}/{key}"

    def camera(self, camera: str, stream: str) -> str:
        return f"{self.prefix}/{check_name(camera, 'camera')}/{stream}"

    def image(self, camera: str) -> str:
        return self.camera(camera, "image")

    def camera_info(self, camera: str) -> str:
        return self.camera(camera, "camera_info")

    def calibration(self, camera: str) -> str:
        return self.camera(camera, "calibration")

    def truth(self, camera: str) -> str:
        return self.camera(camera, "truth")

    def markers(self, camera: str) -> str:
        return self.camera(camera, "markers")

    def blobs(self, camera: str) -> str:
        return self.camera(camera, "blobs")

    def keypoints(self, camera: str) -> str:
        return self.camera(camera, "keypoints")

    def echo(self, camera: str) -> str:
        return self.camera(camera, "echo")

    def overlay(self, camera: str) -> str:
        """The camera's frames with a cube and axes drawn on each tracked target (marker_pose ``overlay``)."""
        return self.camera(camera, "overlay")

    def keyframes(self, camera: str) -> str:
        """The keyframe poses of the map a SLAM node builds from the camera's frames."""
        return self.camera(camera, "keyframes")

    def trajectory(self, camera: str) -> str:
        """The final trajectory of the map a SLAM node builds from the camera's frames (at its end)."""
        return self.camera(camera, "trajectory")

    def camera_map(self, camera: str) -> str:
        """The points of the map a SLAM node builds from the camera's frames (``map`` is the rig's)."""
        return self.camera(camera, "map")

    def timings(self, camera: str) -> str:
        """How long each stage of the processing of the camera's frames took (a SLAM node's StageTimings)."""
        return self.camera(camera, "timings")

    def targets(self, camera: str) -> str:
        """The image targets a features node poses in the camera's frames (``ImageTargets``), published and answered."""
        return self.camera(camera, "targets")

    def slam_pose(self, camera: str) -> str:
        """The camera's pose in the map a SLAM node builds from its frames."""
        return self.pose(f"slam/{check_name(camera, 'camera')}")

    def pose(self, target: str) -> str:
        return f"{self.prefix}/pose/{check_name(target, 'target', segments=True)}"

    def poses(self) -> str:
        """Every pose of the rig."""
        return f"{self.prefix}/pose/**"

    def pose_pattern(self, target: str) -> str:
        """Poses of the targets matching ``target``: a target name whose segments may be ``*``
        (one segment) or ``**`` (any number), e.g. ``cam0/marker/*``, ``cam0/**`` or ``**``."""
        for part in target.split("/"):
            if part not in ("*", "**"):
                check_name(part, "target")
        return f"{self.prefix}/pose/{target}"

    def target(self, key: str) -> str:
        """The target name of a pose key of this rig (``ar/rig0/pose/cam0/marker/7`` -> ``cam0/marker/7``)."""
        head = f"{self.prefix}/pose/"
        if not key.startswith(head) or len(key) == len(head):
            raise ValueError(f"{key!r} is not a pose key of {self.prefix!r}")
        return key[len(head):]

    def bodies(self) -> str:
        return f"{self.prefix}/bodies"

    def map(self) -> str:
        return f"{self.prefix}/map"

    def points(self) -> str:
        """The 3D points a rigid-body tracker triangulates at each instant."""
        return f"{self.prefix}/points"

    def static_transforms(self, node: str) -> str:
        """The static transforms ``node`` publishes (once) and answers (queryable) for late joiners."""
        return f"{self.prefix}/tf_static/{check_name(node, 'node name')}"

    def rig_static_transforms(self) -> str:
        """Static transforms of every node of the rig (query this to gather them all)."""
        return f"{self.prefix}/tf_static/*"

    def latched(self) -> tuple[str, ...]:
        """Key expressions of the rig's static data: published once and answered on request, so that a
        subscriber that comes later (a recorder, a viewer) asks for what it missed."""
        return self.rig_static_transforms(), self.every_camera("targets")

    def node(self, name: str) -> str:
        """The node's liveliness token."""
        return f"{self.prefix}/node/{check_name(name, 'node name')}"

    def stats(self, name: str) -> str:
        return f"{self.node(name)}/stats"

    def state(self, name: str) -> str:
        return f"{self.node(name)}/state"

    def errors(self, name: str) -> str:
        return f"{self.node(name)}/errors"

    def ack(self, name: str) -> str:
        """The frames ``name`` has dealt with (``FlowAck``): the credits a lossless source waits for."""
        return f"{self.node(name)}/ack"

    def end(self, name: str) -> str:
        """``name``'s end of stream (``FlowEnd``), published and answered (queryable) once it is done."""
        return f"{self.node(name)}/end"

    def client(self, client_id: str) -> str:
        """A client app's liveliness token."""
        return f"{self.prefix}/client/{check_name(client_id, 'client id')}"

    def client_state(self, client_id: str) -> str:
        return f"{self.client(client_id)}/state"

    def all_client_states(self) -> str:
        """State queryables of every client app in the namespace, any rig."""
        return f"{self.namespace}/*/client/*/state"

    def split_client(self, key: str) -> tuple[str, str]:
        """``(rig, client id)`` of a client key (token or state) in this namespace."""
        return self._split(key, "client")

    def every_camera(self, stream: str) -> str:
        """``stream`` (``image``, ``markers``, ...) of every camera of the rig."""
        return f"{self.prefix}/*/{check_name(stream, 'stream')}"

    def every_node(self, stream: str) -> str:
        """``stream`` (``stats``, ``errors``) of every node of the rig."""
        return f"{self.prefix}/node/*/{check_name(stream, 'stream')}"

    def control(self, name: str) -> str:
        """The node's control queryable (``ReplayControl`` -> ``ReplayStatus`` for replay)."""
        return f"{self.node(name)}/control"

    def config(self, name: str) -> str:
        """The node's config queryable (live parameter changes)."""
        return f"{self.node(name)}/config"

    def supervisor(self, pipeline: str) -> str:
        """The health queryable of the ``artrack up`` process running ``pipeline`` (its file's stem)."""
        return f"{self.prefix}/supervisor/{check_name(pipeline, 'pipeline name')}"

    def supervisors(self) -> str:
        """Health queryables of every ``artrack up`` process of the rig."""
        return f"{self.prefix}/supervisor/*"

    def everything(self) -> str:
        """Every key of this rig."""
        return f"{self.prefix}/**"

    def whole_namespace(self) -> str:
        """Every key of every rig in the namespace."""
        return f"{self.namespace}/**"

    def all_node_keys(self) -> str:
        """Every node key (stats, state, errors, control) of every rig in the namespace."""
        return f"{self.namespace}/*/node/**"

    def all_nodes(self) -> str:
        """Liveliness tokens of every node in the namespace, any rig."""
        return f"{self.namespace}/*/node/*"

    def all_states(self) -> str:
        """State queryables of every node in the namespace, any rig."""
        return f"{self.namespace}/*/node/*/state"

    def all_stats(self) -> str:
        return f"{self.namespace}/*/node/*/stats"

    def all_poses(self) -> str:
        """Poses of every target of every rig in the namespace."""
        return f"{self.namespace}/*/pose/**"

    def all_supervisors(self) -> str:
        """Health queryables of every ``artrack up`` process in the namespace, any rig."""
        return f"{self.namespace}/*/supervisor/*"

    def all_calibrations(self) -> str:
        """Calibration queryables of every camera of every rig in the namespace."""
        return f"{self.namespace}/*/*/calibration"

    def all_static_transforms(self) -> str:
        """Static transforms of every node of every rig in the namespace."""
        return f"{self.namespace}/*/tf_static/*"

    def all_clients(self) -> str:
        """Liveliness tokens of every client app in the namespace, any rig."""
        return f"{self.namespace}/*/client/*"

    def split_node(self, key: str) -> tuple[str, str]:
        """``(rig, node name)`` of a node key (token, stats or state) in this namespace."""
        return self._split(key, "node")

    def _split(self, key: str, kind: str) -> tuple[str, str]:
        """``(rig, name)`` of ``<namespace>/<rig>/<kind>/<name>[/...]``; ValueError for any other key."""
        rest = key.removeprefix(self.namespace + "/").split("/")
        if not key.startswith(self.namespace + "/") or len(rest) < 3 or rest[1] != kind:
            raise ValueError(f"{key!r} is not a {kind} key under {self.namespace!r}")
        return rest[0], rest[2]
