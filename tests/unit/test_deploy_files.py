"""docker/ checked with the project's own code: what would only break on a Docker or systemd host.

Every artrack compose service must run a real ``artrack`` command on a pipeline that validates,
with environment variables the bus reads and volumes that exist; the router config must parse
with zenoh and keep multicast scouting off; the image must not run as root and its healthcheck
must be a command artrack's parser accepts; the systemd unit must start ``artrack up`` sandboxed
with a SIGHUP reload.
"""

from __future__ import annotations

import configparser
import importlib.metadata
import json
import shlex
from pathlib import PurePosixPath

import pytest
import zenoh

from services.bus.session import BusConfig
from services.cli import parser
from services.launcher.pipeline import PipelineError, read_pipeline
from services.runtime.logs import FORMAT_ENV, LEVEL_ENV, log_format
from tests.deploy_files import DOCKER, ROUTER, artrack_services, compose, host_pipeline, instruction

LOG_ENV = {FORMAT_ENV, LEVEL_ENV}


def commands() -> list[tuple[str, list[str]]]:
    """``(where, argv after artrack)`` of every artrack service, the camera override included."""
    found = [(name, service["command"]) for name, service in artrack_services().items()]
    found += [(f"compose.camera.yaml {name}", service["command"])
              for name, service in compose("compose.camera.yaml")["services"].items()]
    return found


def test_the_image_runs_artrack_as_a_user_that_is_not_root():
    assert json.loads(instruction("ENTRYPOINT")[-1]) == ["artrack"]
    user = instruction("USER")[-1].split(":")[0]
    assert user not in ("root", "0")
    assert instruction("FROM")[0].startswith("${PYTHON_IMAGE}")
    assert any(rest.startswith("PYTHON_IMAGE=python:3.11-slim") for rest in instruction("ARG"))


def test_the_image_installs_the_project_without_the_dev_extra():
    install = " ".join(instruction("RUN"))
    assert "pip install" in install and "[dev]" not in install and ".[" not in install


def test_every_artrack_service_runs_a_pipeline_that_validates():
    for where, argv in commands():
        args = parser().parse_args(argv)
        assert args.command == "up", where
        pipeline = host_pipeline(str(args.pipeline))
        assert pipeline.is_file(), f"{where}: {pipeline} is not in docker/pipelines/"
        try:
            spec = read_pipeline(pipeline)
        except PipelineError as exc:
            pytest.fail(f"{where}: {exc}")
        assert spec.bus == {}, f"{where}: the container's environment must choose the bus, not {pipeline.name}"


def test_the_pipelines_cover_capture_tracking_recording_and_viewing():
    kinds = {node.kind for _, argv in commands()
             for node in read_pipeline(host_pipeline(argv[1])).nodes.values()}
    assert {"capture", "marker_pose", "recorder", "viewer"} <= kinds


def test_services_join_the_router_in_client_mode_with_variables_the_bus_reads():
    router_port = zenoh.Config.from_file(str(DOCKER / "zenoh-router.json5")).get_json("listen/endpoints")
    port = json.loads(router_port)[0].rsplit(":", 1)[1]
    for name, service in artrack_services().items():
        environment = service["environment"]
        unknown = set(environment) - set(BusConfig.ENVIRONMENT.variables()) - LOG_ENV
        assert not unknown, f"{name}: no artrack code reads {sorted(unknown)}"
        if FORMAT_ENV in environment:
            assert log_format(str(environment[FORMAT_ENV])) == "json", name
        bus = BusConfig.from_env({key: str(value) for key, value in environment.items()})
        assert bus.mode == "client", name
        assert bus.connect == (f"tcp/{ROUTER}:{port}",), name
        assert ROUTER in service["depends_on"], name


def test_volumes_are_declared_and_mounted_where_the_image_and_pipelines_write():
    document = compose()
    declared = set(document["volumes"])
    image_volumes = set(json.loads(instruction("VOLUME")[-1]))
    for name, service in document["services"].items():
        for volume in service.get("volumes", ()):
            source, target = volume.split(":")[:2]
            if source.startswith("."):
                assert (DOCKER / source).exists(), f"{name}: bind source {source} is missing"
            else:
                assert source in declared, f"{name}: volume {source} is not declared"
                assert target in image_volumes, f"{name}: {target} is not a VOLUME of the image"
    recorder = artrack_services()["recorder"]
    out = next(iter(read_pipeline(host_pipeline(recorder["command"][1])).nodes.values())).params["out"]
    mounted = {volume.split(":")[1] for volume in recorder["volumes"]}
    assert str(PurePosixPath(out).parent) in mounted


def test_the_router_config_parses_with_zenoh_and_keeps_scouting_off():
    config = zenoh.Config.from_file(str(DOCKER / "zenoh-router.json5"))
    assert json.loads(config.get_json("mode")) == "router"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/[::]:7447"]
    router = compose()["services"][ROUTER]
    mounted = {volume.split(":")[1] for volume in router["volumes"]}
    assert router["command"][-1] in mounted


def test_the_router_image_matches_the_zenoh_the_project_installs():
    tag = compose()["services"][ROUTER]["image"]
    image, _, version = tag.partition(":")
    assert image == "eclipse/zenoh"
    installed = importlib.metadata.version("eclipse-zenoh")
    assert version.split(".")[:2] == installed.split(".")[:2] == ["1", "10"]


def test_the_healthcheck_is_a_command_artrack_parses():
    options, _, command = instruction("HEALTHCHECK")[-1].partition(" CMD ")
    argv = json.loads(command)
    assert argv[0] == "artrack" and "--interval" in options
    args = parser().parse_args(argv[1:])
    assert args.command == "status" and args.check and args.here


def unit() -> configparser.ConfigParser:
    config = configparser.ConfigParser(interpolation=None, strict=False)
    config.optionxform = str
    config.read(DOCKER / "artrack.service")
    return config


def test_the_systemd_unit_runs_artrack_up_sandboxed_as_its_own_user():
    service = unit()["Service"]
    program, *argv = shlex.split(service["ExecStart"])
    assert PurePosixPath(program).name == "artrack"
    args = parser().parse_args(argv)
    assert args.command == "up" and str(args.pipeline) == "/etc/artrack/pipeline.toml"
    assert service["User"] not in ("root", "0")
    assert service["Restart"] == "on-failure"
    assert service["ExecReload"].split()[-2:] == ["-HUP", "$MAINPID"]
    assert service["StandardOutput"] == "journal"
    assert (service["NoNewPrivileges"], service["ProtectSystem"], service["ProtectHome"]) == ("yes", "strict", "yes")
    assert "artrack" in service["StateDirectory"].split()
    # The venv is read-only under ProtectSystem=strict: numba's cache of the compiled kernels goes to the unit's
    # cache directory, which systemd makes writable.
    environment = dict(pair.split("=", 1) for pair in shlex.split(service["Environment"]))
    assert "artrack" in service["CacheDirectory"].split()
    assert PurePosixPath(environment["NUMBA_CACHE_DIR"]).is_relative_to("/var/cache/artrack")


def test_the_image_and_the_unit_set_only_variables_artrack_reads():
    image = dict(pair.split("=", 1) for line in instruction("ENV") for pair in shlex.split(line))
    service = dict(pair.split("=", 1) for pair in shlex.split(unit()["Service"]["Environment"]))
    for where, environment in (("Dockerfile", image), ("artrack.service", service)):
        ours = {name: value for name, value in environment.items() if name.startswith("ARTRACK_")}
        assert ours, where
        read = set(BusConfig.ENVIRONMENT.variables()) | LOG_ENV
        assert not set(ours) - read, f"{where}: no artrack code reads {sorted(ours)}"
        assert log_format(ours.get(FORMAT_ENV)) == "json", where
