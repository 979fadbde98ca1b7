"""The bus options of every command that joins the bus (--connect, --rig, TLS, ...) and the bus settings they
give, over the environment and a pipeline file's ``[bus]``."""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Mapping
from pathlib import Path

from pydantic import ValidationError

from services.bus.session import LOCAL_ROUTER, BusConfig

log = logging.getLogger("artrack")


def add_bus_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("bus (default: the local router on " + LOCAL_ROUTER + ", started on demand)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="router or peer to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; env ARTRACK_CONNECT)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help="endpoint to listen on (repeatable; env ARTRACK_LISTEN)")
    group.add_argument("--mode", choices=("peer", "client"), help="Zenoh mode (env ARTRACK_MODE; default peer)")
    group.add_argument("--zenoh-config", type=Path, metavar="FILE",
                       help="a Zenoh JSON5/YAML config, used as is but for the security options (env ZENOH_CONFIG)")
    group.add_argument("--namespace", help="key namespace (env ARTRACK_NAMESPACE; default ar)")
    group.add_argument("--rig", help="rig name (env ARTRACK_RIG; default rig0)")
    add_tls_options(group)
    group.add_argument("--user", help="user name the router checks (env ARTRACK_USER; needs --mode client)")
    group.add_argument("--password-file", type=Path, metavar="FILE",
                       help="file holding the user's password (env ARTRACK_PASSWORD_FILE, or ARTRACK_PASSWORD)")


def add_tls_options(group: argparse._ArgumentGroup) -> None:
    group.add_argument("--tls-ca", type=Path, metavar="PEM", help="root CA of tls/ endpoints (env ARTRACK_TLS_ROOT_CA)")
    group.add_argument("--tls-cert", type=Path, metavar="PEM", help="own certificate (env ARTRACK_TLS_CERT)")
    group.add_argument("--tls-key", type=Path, metavar="PEM", help="own private key (env ARTRACK_TLS_KEY)")
    group.add_argument("--tls-mutual", action="store_true", default=None,
                       help="mutual TLS: present the certificate / require one (env ARTRACK_TLS_MUTUAL)")


def security_options(args: argparse.Namespace) -> dict[str, object]:
    """The security options given on the command line, by ``Security`` field."""
    given = {"root_ca": args.tls_ca, "cert": args.tls_cert, "key": args.tls_key, "mutual": args.tls_mutual,
             "user": getattr(args, "user", None), "password_file": getattr(args, "password_file", None)}
    return {field: value for field, value in given.items() if value is not None}


def bus_config(args: argparse.Namespace, *, daemon: bool = False, defaults: Mapping[str, object] | None = None,
         source: str | None = None) -> BusConfig:
    """Bus settings, each field from: its command-line option, else its environment variable, else
    ``defaults`` (the ``[bus]`` of pipeline file ``source``), else the field's default.

    When the environment overrides a value of file ``source``, one line says so. A ``daemon``
    (a node, ``up``) waits for its router unless ``ARTRACK_RETRY=0``."""
    defaults = {**({"retry": True} if daemon else {}), **(defaults or {})}
    given = {"connect": tuple(args.connect or ()), "listen": tuple(args.listen or ()), "mode": args.mode,
             "zenoh_config": args.zenoh_config, "namespace": args.namespace, "rig": args.rig,
             "security": security_options(args) or None}
    # Only options actually given override what is below them: an unset option must not erase a value.
    overrides = {k: v for k, v in given.items() if v is not None and v != ()}
    try:
        bus = BusConfig.from_env(defaults=defaults, **overrides)
    except ValidationError as exc:
        variables = {field: name for name, field in BusConfig.ENVIRONMENT.variables().items()}
        problems = []
        for problem in exc.errors():
            field = ".".join(str(part) for part in problem["loc"])
            message = problem["msg"].removeprefix("Value error, ")
            if not field:
                problems.append(message)
                continue
            where = f"{field} (env {variables[field]})" if field in variables else field
            problems.append(f"{where}: {message} (given {problem['input']!r})")
        raise ValueError("bus settings: " + "; ".join(problems)) from exc
    beaten = bus.overridden(defaults, **overrides) if source is not None else {}
    if beaten:
        said = ", ".join(f"{field} by {variable}" + ("" if field.startswith("security") else f"={os.environ[variable]}")
                         for variable, field in beaten.items())
        log.warning("%s: the environment overrides [bus] %s (a flag beats the environment, which beats the file)",
                    source, said)
    return bus
