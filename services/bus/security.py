"""Transport security of a Zenoh session: TLS and user/password authentication.

One ``Security`` serves client apps, nodes and the router alike and renders the Zenoh 1.10
config entries under ``transport/link/tls`` and ``transport/auth/usrpwd``:

* ``root_ca``: the CA that signed the router's certificate (and, with ``mutual``, the
  clients'); a session that connects to a ``tls/`` endpoint needs it.
* ``cert`` + ``key``: this process's certificate and private key (PEM), used to listen on a
  ``tls/`` endpoint (a router) and, with ``mutual``, to prove who a client is (mutual TLS;
  the router's access rules can then name the certificate's common name).
* ``user`` + ``password`` or ``password_file``: credentials the router checks against its
  users file. They need client mode: a peer would also meet other peers directly, past the
  router's checks, so secure mode is client mode through a router.

The password is read from ``password_file`` when the config is rendered, so it need not sit
in the environment of every child process.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

TLS = "tls/"


class Security(BaseModel):
    """TLS files and credentials of one session (see the module docstring); empty = plain TCP.

    Validation errors leave out the input, which may hold the password.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", hide_input_in_errors=True)

    root_ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    mutual: bool = False
    user: str | None = None
    password: str | None = Field(default=None, repr=False)
    password_file: Path | None = None

    @model_validator(mode="after")
    def _consistent(self) -> Security:
        for what, path in (("TLS root CA", self.root_ca), ("TLS certificate", self.cert),
                           ("TLS private key", self.key), ("password file", self.password_file)):
            if path is not None and not path.is_file():
                raise ValueError(f"{what} {path} {'is not a file' if path.exists() else 'does not exist'}")
        if (self.cert is None) != (self.key is None):
            raise ValueError("a TLS certificate and its private key go together: give both or neither")
        if self.mutual and (self.cert is None or self.root_ca is None):
            raise ValueError("mutual TLS needs this side's certificate and key and the root CA")
        if self.password is not None and self.password_file is not None:
            raise ValueError("give a password or a password file, not both")
        if (self.user is None) != (self.password is None and self.password_file is None):
            raise ValueError("user/password authentication needs both a user and a password (or password file)")
        return self

    @property
    def authenticates(self) -> bool:
        """True when these settings carry user credentials."""
        return self.user is not None

    def secret(self) -> str | None:
        """The password, read from ``password_file`` (surrounding whitespace dropped) when that is
        how it was given; ValueError when the file cannot be read or holds nothing."""
        if self.password_file is None:
            return self.password
        try:
            password = self.password_file.read_text().strip()
        except OSError as exc:
            raise ValueError(f"password file {self.password_file}: {exc.strerror}") from exc
        if not password:
            raise ValueError(f"password file {self.password_file} is empty")
        return password

    def check(self, mode: str, listen: tuple[str, ...], connect: tuple[str, ...]) -> None:
        """Raise ValueError when these settings cannot work with ``mode`` and the endpoints."""
        if self.authenticates and mode == "peer":
            raise ValueError("user/password authentication needs client mode (--mode client, ARTRACK_MODE=client): "
                             "secure deployments reach each other through a router")
        for endpoint in connect:
            if endpoint.startswith(TLS) and self.root_ca is None:
                raise ValueError(f"endpoint {endpoint} is TLS: give the root CA that signed the router's "
                                 "certificate (--tls-ca, ARTRACK_TLS_ROOT_CA)")
        for endpoint in listen:
            if endpoint.startswith(TLS) and self.cert is None:
                raise ValueError(f"listening on {endpoint} needs a TLS certificate and key (--tls-cert, --tls-key)")

    def apply(self, config: zenoh.Config) -> None:
        """Write these settings into ``config`` (only what is set)."""
        entries: dict[str, object] = {}
        if self.root_ca is not None:
            entries["transport/link/tls/root_ca_certificate"] = str(self.root_ca)
        if self.cert is not None and self.key is not None:
            for side in ("listen", "connect"):
                entries[f"transport/link/tls/{side}_certificate"] = str(self.cert)
                entries[f"transport/link/tls/{side}_private_key"] = str(self.key)
        if self.mutual:
            entries["transport/link/tls/enable_mtls"] = True
        if self.user is not None:
            entries["transport/auth/usrpwd/user"] = self.user
            entries["transport/auth/usrpwd/password"] = self.secret()
        for key, value in entries.items():
            config.insert_json5(key, json.dumps(value))


def masked(value: Any) -> Any:
    """``value`` with every ``password`` entry of its dicts (at any depth) shown as ``***``: what a
    validation error may echo of settings given as plain dicts."""
    if isinstance(value, dict):
        return {key: "***" if key == "password" and item is not None else masked(item) for key, item in value.items()}
    return value

