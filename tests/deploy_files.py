"""docker/'s files read for the tests: the compose services, the image's pipelines, the Dockerfile."""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import yaml

DOCKER = Path(__file__).resolve().parents[1] / "docker"
IMAGE_PIPELINES = PurePosixPath("/etc/artrack/pipelines")
ROUTER = "zenoh"


def compose(name: str = "compose.yaml") -> dict:
    return yaml.safe_load((DOCKER / name).read_text())


def artrack_services() -> dict[str, dict]:
    return {name: service for name, service in compose()["services"].items() if name != ROUTER}


def dockerfile() -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` of the Dockerfile, continuation lines joined, comments dropped."""
    instructions, pending = [], ""
    for line in (DOCKER / "Dockerfile").read_text().splitlines():
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        pending += line.rstrip("\\").strip() + " "
        if not line.endswith("\\"):
            keyword, _, rest = pending.strip().partition(" ")
            instructions.append((keyword.upper(), rest.strip()))
            pending = ""
    return instructions


def instruction(name: str) -> list[str]:
    return [rest for keyword, rest in dockerfile() if keyword == name]


def host_pipeline(path: str) -> Path:
    """The file in docker/pipelines/ that the image holds at ``path``."""
    return DOCKER / "pipelines" / PurePosixPath(path).relative_to(IMAGE_PIPELINES)
