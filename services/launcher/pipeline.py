"""Pipelines: which nodes run, in which processes, and what each reads and writes.

``artrack up FILE.toml`` reads a pipeline from a file, ``artrack run TRACKER`` builds one from
a tracker template and flags (``--save-pipeline FILE.toml`` writes it out); both give the same
``PipelineSpec``. The file::

    [bus]               # optional, any BusConfig field: namespace, rig, connect, listen, mode
    rig = "demo"

    [supervisor]        # optional, any SupervisorSettings field: back-off, restart budget, grace
    max_restarts = 5    # restarts allowed within window_s; past that the node is failed, left down
    window_s = 60

    [flow]              # optional (services.launcher.flow): lossless, realtime or auto (the default:
    mode = "auto"       # lossless when every source is finite), and how far a lossless source may
    window = 4          # send ahead of its slowest node

    [nodes.cam]         # one table per node; the table name is the node's name
    kind = "capture"    # a node kind (``artrack kinds`` lists them)
    restart = true      # restart it when it dies (default)
    fps = 30            # every other key is a parameter of the kind
    outputs = ["cam0/image", "cam0/camera_info", "cam0/truth"]   # optional: the keys it writes

    [nodes.echo]
    kind = "echo"
    process = "cam"     # optional: run in the process of that name, beside the nodes that name it too
    inputs = ["cam0/image"]                                      # optional: the keys it reads
    nice = -5           # optional: its process's priority, and the CPUs it may run on
    cpus = [1]          # (``services.launcher.scheduling``)

Each node runs in a process of its own unless ``process`` names a process group: the nodes that
name the same one run in one process, where the messages between them pass by reference
(``services.runtime.group``). A lone node's process is named after it, so a group may not take
the name of a node outside it.

``inputs`` and ``outputs`` (keys relative to ``<namespace>/<rig>/``) follow from the kind and
its parameters; a file may state them, and then they must agree, so a reader of the file sees
the wiring and a file edited out of step with it is refused. The whole file is validated,
node parameters included, before any process starts; the first error names the file, the
field and the reason.
"""

from __future__ import annotations

import functools
import json
import sys
import tomllib
from pathlib import Path
from typing import Any

import tomli_w
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, field_validator

from protocol.keys import check_name
from services.bus.session import BusConfig
from services.launcher.flow import FlowSettings, plans
from services.launcher.kinds import kind
from services.launcher.scheduling import NICE_RANGE, Scheduling, check_scheduling
from services.launcher.supervisor import ProcessSpec, SupervisorSettings
from services.runtime.flow import FlowPlan
from services.runtime.params import flat_dump

RESERVED = ("kind", "restart", "process", "inputs", "outputs", "nice", "cpus")
"""Keys of a node table that are not parameters of its kind."""


class PipelineError(ValueError):
    """A pipeline that cannot run; the message names the file, field and reason."""


class NodeSpec(BaseModel):
    """One node of a pipeline: its kind, restart policy, process group, declared keys, the priority and CPUs it
    asks for its process (``services.launcher.scheduling``) and the kind's parameters (extra keys)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    kind: str
    restart: bool = True
    process: str | None = None
    inputs: tuple[str, ...] | None = None
    outputs: tuple[str, ...] | None = None
    nice: int | None = Field(None, ge=NICE_RANGE[0], le=NICE_RANGE[1])
    cpus: tuple[int, ...] | None = None

    @field_validator("cpus")
    @classmethod
    def _cpus(cls, cpus: tuple[int, ...] | None) -> tuple[int, ...] | None:
        if cpus is not None and (not cpus or min(cpus) < 0 or len(set(cpus)) != len(cpus)):
            raise ValueError(f"give one or more different CPU numbers, 0 or more, got {list(cpus)}")
        return None if cpus is None else tuple(sorted(cpus))

    @property
    def params(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class PipelineSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    bus: dict[str, Any] = Field(default_factory=dict)
    supervisor: SupervisorSettings = Field(default_factory=SupervisorSettings)
    flow: FlowSettings = Field(default_factory=FlowSettings)
    nodes: dict[str, NodeSpec] = Field(min_length=1)

    @field_validator("nodes")
    @classmethod
    def _names(cls, nodes: dict[str, NodeSpec]) -> dict[str, NodeSpec]:
        for name, node in nodes.items():
            check_name(name, "node name")
            if node.process is not None:
                check_name(node.process, f"nodes.{name}.process")
                if node.process in nodes and nodes[node.process].process not in (None, node.process):
                    raise ValueError(f"nodes.{name}.process: {node.process!r} is the name of a node in another "
                                     f"process (a lone node's process is named after it): name the group otherwise")
        placed: dict[str, tuple[str, tuple[int, ...]]] = {}
        for name, node in nodes.items():
            if node.cpus is None:
                continue
            other, cpus = placed.setdefault(node.process or name, (name, node.cpus))
            if cpus != node.cpus:
                raise ValueError(f"nodes.{name}.cpus {list(node.cpus)}: node {other} of the same process asks for "
                                 f"{list(cpus)}: the nodes of one process share its CPUs")
        return nodes

    def groups(self) -> dict[str, tuple[str, ...]]:
        """``{process: (node, ...)}``: the nodes each process runs, in the file's order; a node that names no
        process runs alone in one named after it."""
        groups: dict[str, list[str]] = {}
        for name, node in self.nodes.items():
            groups.setdefault(node.process or name, []).append(name)
        return {process: tuple(names) for process, names in groups.items()}

    def process_of(self, node: str) -> str:
        """The name of the process node ``node`` runs in."""
        return self.nodes[node].process or node

    def scheduling(self, process: str) -> Scheduling:
        """What process ``process`` asks of the scheduler: the most urgent ``nice`` of its nodes and their
        ``cpus`` (one set, or none)."""
        members = [self.nodes[name] for name in self.groups()[process]]
        nices = [node.nice for node in members if node.nice is not None]
        cpus = next((node.cpus for node in members if node.cpus is not None), None)
        return Scheduling(min(nices) if nices else None, cpus)

    def sources(self) -> list[str]:
        """The nodes that read nothing from the bus (captures, replays): where data enters."""
        return [name for name, node in self.nodes.items() if not node.inputs]

    def flow_plans(self) -> dict[str, FlowPlan]:
        """Each node's part in the pipeline's flow (a resolved pipeline: its nodes' keys are filled in)."""
        return plans(self.flow, {name: (node.kind, node.params, node.inputs or (), node.outputs or ())
                                 for name, node in self.nodes.items()})

    def lossless(self) -> bool:
        """Whether the pipeline's frames flow lossless (its flow mode, or auto and every source finite)."""
        return any(plan.lossless for plan in self.flow_plans().values())


def describe(error: ValidationError, prefix: str = "") -> str:
    """One line per problem: ``field.path: reason``."""
    lines = []
    for problem in error.errors():
        path = ".".join(str(p) for p in (prefix, *problem["loc"]) if p != "")
        lines.append(f"{path or '(top level)'}: {problem['msg']}")
    return "; ".join(lines)


def resolved(spec: PipelineSpec, where: str = "pipeline") -> PipelineSpec:
    """``spec`` with every node's parameters validated by its kind and its inputs and outputs filled in.

    Raises PipelineError naming ``where``, the node and the field: an unknown kind, a bad
    parameter, or stated keys that differ from what the kind reads and writes with those parameters.
    """
    try:
        BusConfig.model_validate(spec.bus)
    except ValidationError as exc:
        raise PipelineError(f"{where}: {describe(exc, 'bus')}") from exc
    nodes = {}
    for name, node in spec.nodes.items():
        try:
            node_kind = kind(node.kind)
            params = node_kind.validate(node.params)
        except ValidationError as exc:
            raise PipelineError(f"{where}: {describe(exc, f'nodes.{name}')}") from exc
        except ValueError as exc:
            raise PipelineError(f"{where}: nodes.{name}: {exc}") from exc
        inputs, outputs = node_kind.keys(params)
        for field, stated, derived in (("inputs", node.inputs, inputs), ("outputs", node.outputs, outputs)):
            if stated is not None and tuple(stated) != derived:
                raise PipelineError(f"{where}: nodes.{name}.{field}: a {node.kind} node with these parameters has "
                                    f"{field} {list(derived)}, the file says {list(stated)} (keys follow from the "
                                    f"parameters: change those, or drop {field})")
        nodes[name] = node.model_copy(update={"inputs": inputs, "outputs": outputs})
    return spec.model_copy(update={"nodes": nodes})


def preflight(spec: PipelineSpec, where: str = "pipeline") -> None:
    """Run every node kind's ``check`` on its node (files, folders, dictionaries the parameters name), hold each
    node's own calibration against the frame sizes the sources tell before they start (``NodeKind.check_frames``,
    ``SourceRole.sizes``), then run each kind's ``prepare`` once (compiled code built before a node needs it), so
    a pipeline that cannot start, or whose node would stop at its first frame, is refused before any process
    starts, and before any code is compiled: PipelineError naming ``where``, the node and the reason. First of
    all, a priority or CPUs asked for that this machine does not allow are refused (``check_scheduling``)."""
    try:
        check_scheduling({name: Scheduling(node.nice, node.cpus) for name, node in spec.nodes.items()})
    except ValueError as exc:
        raise PipelineError(f"{where}: {exc}") from exc
    for name, node in spec.nodes.items():
        node_kind = kind(node.kind)
        try:
            node_kind.preflight(node_kind.validate(node.params))
        except (ValueError, OSError) as exc:
            raise PipelineError(f"{where}: nodes.{name}: {exc}") from exc
    sizes = functools.cache(functools.partial(_frame_sizes, spec, where))
    for name, node in spec.nodes.items():
        node_kind = kind(node.kind)
        if node_kind.check_frames is None:
            continue
        try:
            node_kind.check_frames(node_kind.validate(node.params), sizes)
        except PipelineError:
            raise  # a source that could not tell its sizes: already named
        except (ValueError, OSError) as exc:
            raise PipelineError(f"{where}: nodes.{name}: {exc}") from exc
    for prepare in dict.fromkeys(k.prepare for k in map(kind, (n.kind for n in spec.nodes.values())) if k.prepare):
        prepare()


def _frame_sizes(spec: PipelineSpec, where: str) -> dict[str, tuple[int, int]]:
    """``{camera: (width, height)}`` of the frames the nodes of ``spec`` send, as far as their kinds tell before
    they start (``SourceRole.sizes``: scenes, image folders, video files, recordings); PipelineError naming
    ``where`` and the node when one cannot tell."""
    sizes: dict[str, tuple[int, int]] = {}
    for name, node in spec.nodes.items():
        node_kind = kind(node.kind)
        if node_kind.source is None:
            continue
        try:
            sizes.update(node_kind.source.sizes(node_kind.validate(node.params)))
        except (ValueError, OSError) as exc:
            raise PipelineError(f"{where}: nodes.{name}: {exc}") from exc
    return sizes


def read_pipeline(path: Path) -> PipelineSpec:
    """Load and fully validate a pipeline file (raises PipelineError)."""
    try:
        document = tomllib.loads(path.read_text())
    except OSError as exc:
        raise PipelineError(f"{path}: cannot read: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise PipelineError(f"{path}: not valid TOML: {exc}") from exc
    try:
        spec = PipelineSpec.model_validate(document)
    except ValidationError as exc:
        raise PipelineError(f"{path}: {describe(exc)}") from exc
    return resolved(spec, str(path))


def to_toml(spec: PipelineSpec, header: str = "") -> str:
    """The pipeline file of ``spec``: what ``read_pipeline`` reads back as the same pipeline;
    ``header`` (lines of text) opens it as comments."""
    document: dict[str, Any] = {}
    if spec.bus:
        document["bus"] = {k: v for k, v in spec.bus.items() if v is not None}
    supervisor = spec.supervisor.model_dump(mode="json", exclude_defaults=True)
    if supervisor:
        document["supervisor"] = supervisor
    flow = spec.flow.model_dump(mode="json", exclude_defaults=True)
    if flow:
        document["flow"] = flow
    document["nodes"] = {}
    for name, node in spec.nodes.items():
        params = flat_dump(kind(node.kind).validate(node.params), mode="json", exclude_unset=True, exclude_none=True)
        table: dict[str, Any] = {"kind": node.kind, **({} if node.restart else {"restart": False}),
                                 **({} if node.process is None else {"process": node.process}),
                                 **({} if node.nice is None else {"nice": node.nice}),
                                 **({} if node.cpus is None else {"cpus": list(node.cpus)}), **params}
        for field in ("inputs", "outputs"):
            if getattr(node, field) is not None:
                table[field] = list(getattr(node, field))
        document["nodes"][name] = table
    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    return comments + ("\n" if comments else "") + tomli_w.dumps(document)


def save_pipeline(spec: PipelineSpec, path: Path, header: str = "") -> None:
    """Write ``spec`` to ``path`` as a pipeline file (ValueError naming the path when it cannot be written)."""
    try:
        path.write_text(to_toml(spec, header))
    except OSError as exc:
        raise PipelineError(f"cannot write {path}: {exc.strerror}") from exc


def node_command(kind_name: str, name: str, params: dict[str, Any], flow: FlowPlan | None = None
                 ) -> tuple[str, ...]:
    """The command that runs one node in its own process (with its part in the flow, when given)."""
    return (sys.executable, "-m", "services.cli", "node", kind_name, "--name", name,
            "--params", json.dumps(params, default=str),
            *(() if flow is None else ("--flow", flow.model_dump_json(exclude_defaults=True))))


class GroupMember(BaseModel):
    """One node of a process group as its command passes it: ``artrack group NAME --nodes JSON``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    kind: str
    params: dict[str, Any] = Field(default_factory=dict)
    flow: FlowPlan = Field(default_factory=FlowPlan)
    source: bool = False


GROUP_MEMBERS = TypeAdapter(list[GroupMember])


def group_command(process: str, members: list[GroupMember]) -> tuple[str, ...]:
    """The command that runs ``members`` in one process named ``process``."""
    return (sys.executable, "-m", "services.cli", "group", process, "--nodes",
            GROUP_MEMBERS.dump_json(members, exclude_defaults=True).decode())


def params_model(kind_name: str) -> type[BaseModel]:
    """The Params model of a node kind (its ``RELOADABLE`` fields may change live)."""
    return kind(kind_name).params


def processes(spec: PipelineSpec, bus: BusConfig, names: list[str] | None = None) -> list[ProcessSpec]:
    """One ProcessSpec per process of the pipeline (or per process of ``names``), sharing ``bus``, each node with
    its flow plan (``spec`` is resolved) and its process the scheduling its nodes ask for. A process restarts when
    it dies unless one of its nodes says ``restart = false``."""
    env = bus.to_env()
    flow = spec.flow_plans()
    sources = set(spec.sources())
    found = []
    for process, members in spec.groups().items():
        if names is not None and process not in names:
            continue
        restart = all(spec.nodes[name].restart for name in members)
        scheduling = spec.scheduling(process)
        if members == (process,):
            node = spec.nodes[process]
            found.append(ProcessSpec(process, node_command(node.kind, process, node.params, flow[process]), env,
                                     restart, scheduling))
            continue
        listed = [GroupMember(name=name, kind=spec.nodes[name].kind, params=spec.nodes[name].params, flow=flow[name],
                              source=name in sources) for name in members]
        found.append(ProcessSpec(process, group_command(process, listed), env, restart, scheduling))
    return found


__all__ = ["GROUP_MEMBERS", "GroupMember", "NodeSpec", "PipelineError", "PipelineSpec", "describe", "group_command",
           "node_command", "params_model",
           "preflight", "processes", "read_pipeline", "resolved", "save_pipeline", "to_toml"]
