"""Reading the project's YAML files (camera_info, rig, bodies, marker maps) with one-line errors."""

from __future__ import annotations

from pathlib import Path

import yaml


def read_yaml(path: str | Path, error: type[ValueError]) -> object:
    """The YAML document in ``path``; ``error`` with one line naming the file when it cannot be read
    or is not valid YAML."""
    try:
        return yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise error(f"{path}: cannot read the file: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from exc
