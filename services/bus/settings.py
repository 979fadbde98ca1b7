"""Where a process finds the bus: the settings client apps and artrack's own processes share.

Three ways to say it, in order of precedence:

1. a Zenoh JSON5/YAML config file (``zenoh_config`` or ``ZENOH_CONFIG``), used as is but for
   the security settings, which are written over it when given;
2. explicit endpoints: ``connect`` (``tcp/HOST:PORT`` of a router or a peer) and ``listen``,
   in ``peer`` or ``client`` mode (``ARTRACK_CONNECT``, ``ARTRACK_LISTEN``, ``ARTRACK_MODE``);
3. nothing: a peer listening on a free loopback port that connects to the local router at
   ``tcp/127.0.0.1:7447``.

``namespace`` and ``rig`` (``ARTRACK_NAMESPACE``, ``ARTRACK_RIG``) say whose keys to use.
Each field is taken from, in order: the value given in code (a command-line flag), the
environment variable, the ``defaults`` a program brings (a pipeline file's ``[bus]``), the
field's default (``from_env``; ``overridden`` names the variables that beat a default).
``security`` (``ARTRACK_TLS_ROOT_CA``, ``ARTRACK_TLS_CERT``, ``ARTRACK_TLS_KEY``,
``ARTRACK_TLS_MUTUAL``, ``ARTRACK_USER``, ``ARTRACK_PASSWORD`` or ``ARTRACK_PASSWORD_FILE``) adds
TLS and credentials to the endpoints' config (see ``services.bus.security``).
Multicast scouting is always off unless a config file turns it on.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Self

import zenoh
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ModelWrapValidatorHandler,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, to_jsonable_python
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict
from zenoh import Session

from protocol.keys import Keys, check_name
from services.bus.security import Security, masked
from services.bus.transport import LOCAL_ROUTER, session_config


class BusError(RuntimeError):
    """The bus could not be opened as configured; the message says what and why."""


def read_zenoh_config(path: Path) -> zenoh.Config:
    """The Zenoh config in the JSON5/YAML file ``path``; BusError when it is missing or invalid."""
    if not path.is_file():
        raise BusError(f"Zenoh config file {path} does not exist")
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise BusError(f"Zenoh config file {path} is invalid: {exc}") from exc


def _nest(values: dict[str, Any], field: str, value: object) -> None:
    """Set ``values[a][b] = value`` for a dotted ``field`` ``a.b``."""
    *parents, last = field.split(".")
    for parent in parents:
        values = values.setdefault(parent, {})
    values[last] = value


def _dotted(values: Mapping[str, Any], field: str) -> object:
    """``values[a][b]`` for a dotted ``field`` ``a.b``; None when absent."""
    for part in field.split("."):
        if not isinstance(values, Mapping) or part not in values:
            return None
        values = values[part]
    return values


Listed = Annotated[tuple[str, ...] | None, NoDecode]
"""A variable holding a comma-separated list (pydantic-settings would otherwise expect JSON)."""


class BusEnvironment(BaseSettings):
    """The environment variables of ``BusSettings``, read by pydantic-settings.

    Each field is named for the settings field it sets (``security__root_ca`` sets
    ``security.root_ca``) and aliased to its variable. Values stay text (lists are split at
    commas): ``BusSettings`` converts and checks them, so an error names its field. Empty
    variables count as unset.
    """

    model_config = SettingsConfigDict(case_sensitive=True, env_ignore_empty=True, extra="ignore", frozen=True)

    mode: str | None = Field(None, alias="ARTRACK_MODE")
    connect: Listed = Field(None, alias="ARTRACK_CONNECT")
    listen: Listed = Field(None, alias="ARTRACK_LISTEN")
    zenoh_config: str | None = Field(None, alias="ZENOH_CONFIG")
    namespace: str | None = Field(None, alias="ARTRACK_NAMESPACE")
    rig: str | None = Field(None, alias="ARTRACK_RIG")
    security__root_ca: str | None = Field(None, alias="ARTRACK_TLS_ROOT_CA")
    security__cert: str | None = Field(None, alias="ARTRACK_TLS_CERT")
    security__key: str | None = Field(None, alias="ARTRACK_TLS_KEY")
    security__mutual: str | None = Field(None, alias="ARTRACK_TLS_MUTUAL")
    security__user: str | None = Field(None, alias="ARTRACK_USER")
    security__password: str | None = Field(None, alias="ARTRACK_PASSWORD")
    security__password_file: str | None = Field(None, alias="ARTRACK_PASSWORD_FILE")

    @field_validator("connect", "listen", mode="before")
    @classmethod
    def _comma_separated(cls, value: object) -> object:
        if isinstance(value, str):
            return tuple(part.strip() for part in value.split(",") if part.strip())
        return value

    @classmethod
    def variables(cls) -> dict[str, str]:
        """Variable -> the dotted settings field it sets."""
        return {str(info.alias): name.replace("__", ".") for name, info in cls.model_fields.items()}

    @classmethod
    def values(cls, environ: Mapping[str, str] | None = None) -> dict[str, Any]:
        """The variables set in ``environ`` (default: the process's environment) as nested settings values."""
        given = None if environ is None else {name: text for name, text in environ.items() if text}
        found = cls() if given is None else cls.model_validate(given)
        values: dict[str, Any] = {}
        for name, value in found.model_dump(exclude_none=True).items():
            _nest(values, name.replace("__", "."), value)
        return values


class BusSettings(BaseModel):
    """Mode, endpoints or config file, namespace, rig and security of one process's Zenoh session."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ENVIRONMENT: ClassVar[type[BusEnvironment]] = BusEnvironment
    """The variables these settings are read from; a subclass with fields of its own names a subclass."""

    mode: Literal["peer", "client"] = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: Path | None = None
    namespace: str = "ar"
    rig: str = "rig0"
    security: Security = Security()

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        return check_name(value, "namespace", segments=True)

    @field_validator("rig")
    @classmethod
    def _rig(cls, value: str) -> str:
        return check_name(value, "rig")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for endpoint in value:
            if "/" not in endpoint:
                raise ValueError(f"endpoint {endpoint!r} must look like tcp/HOST:PORT")
        return value

    @model_validator(mode="after")
    def _secure(self) -> BusSettings:
        if self.zenoh_config is None:
            self.security.check(self.mode, self.listen, self.connect)
        return self

    @model_validator(mode="wrap")
    @classmethod
    def _no_password_in_errors(cls, data: Any, handler: ModelWrapValidatorHandler[BusSettings]) -> BusSettings:
        """Errors show the input they refused, so a password given in a plain dict is masked in them."""
        try:
            return handler(data)
        except ValidationError as exc:
            details = []
            for e in exc.errors():
                detail = InitErrorDetails(type=e["type"], loc=e["loc"], input=masked(e["input"]))
                if "ctx" in e:
                    detail["ctx"] = e["ctx"]
                details.append(detail)
            raise ValidationError.from_exception_data(exc.title, details) from None

    @property
    def keys(self) -> Keys:
        return Keys(self.namespace, self.rig)

    @property
    def uses_local_router(self) -> bool:
        return self.zenoh_config is None and not self.connect

    @property
    def endpoints(self) -> tuple[str, ...]:
        """The endpoints the session connects to; () with a config file (they are the file's)."""
        return () if self.zenoh_config else self.connect or (LOCAL_ROUTER,)

    @property
    def where(self) -> str:
        """Where the session goes, for error messages: the config file or the endpoints."""
        return str(self.zenoh_config) if self.zenoh_config else ", ".join(self.endpoints)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, *, defaults: Mapping[str, object] | None = None,
                 **overrides: object) -> Self:
        """Settings from ``defaults`` (a pipeline file's ``[bus]``), then the environment variables that are
        set (``ENVIRONMENT``, default: the process's environment), then ``overrides`` (None or () = unset).

        A dict value of a nested model (``security={"root_ca": ...}``) updates what the layer
        below said field by field; a model instance replaces it whole.
        """
        values: dict[str, Any] = {}
        for layer in (defaults or {}, cls.ENVIRONMENT.values(environ), overrides):
            for field, value in layer.items():
                if value is None or value == ():
                    continue
                if isinstance(value, Mapping) and isinstance(values.get(field), Mapping):
                    value = {**values[field], **value}
                values[field] = value
        if isinstance(values.get("security"), Mapping):  # validated on its own: its errors hide the password
            values["security"] = Security.model_validate(values["security"])
        return cls.model_validate(values)

    def overridden(self, defaults: Mapping[str, object], environ: Mapping[str, str] | None = None,
                   **overrides: object) -> dict[str, str]:
        """``{variable: field}`` of the environment variables that gave these settings (made by ``from_env``
        with the same arguments) a value other than the one ``defaults`` set (fields ``overrides`` does
        not set itself)."""
        environment = self.ENVIRONMENT.values(environ)
        mine = self.model_dump(mode="json")
        found = {}
        for variable, field in self.ENVIRONMENT.variables().items():
            head, _, rest = field.partition(".")
            own = overrides.get(head)
            if own is not None and own != () and (not rest or not isinstance(own, Mapping) or rest in own):
                continue
            wanted = _dotted(defaults, field)
            if _dotted(environment, field) is not None and wanted is not None and \
                    to_jsonable_python(wanted) != _dotted(mine, field):
                found[variable] = field
        return found

    def to_env(self) -> dict[str, str]:
        """The variables that make ``from_env`` rebuild these settings in a child process."""
        env = {}
        for name, field in self.ENVIRONMENT.variables().items():
            value: Any = self
            for part in field.split("."):
                value = getattr(value, part)
            if isinstance(value, tuple):
                env[name] = ",".join(value)
            elif isinstance(value, bool):
                env[name] = "1" if value else "0"
            elif isinstance(value, float):
                env[name] = repr(value)
            else:
                env[name] = "" if value is None else str(value)
        return env

    def zenoh(self) -> zenoh.Config:
        """The Zenoh config these settings describe (BusError for a missing or invalid file)."""
        if self.zenoh_config is not None:
            config = read_zenoh_config(self.zenoh_config)
            self.security.apply(config)
            return config
        connect = self.connect or (LOCAL_ROUTER,)
        listen = self.listen or (("tcp/127.0.0.1:0",) if self.mode == "peer" else ())
        return session_config(self.mode, listen=listen, connect=connect, security=self.security)

    def open(self) -> Session:
        """Open the session (BusError naming where and why when Zenoh refuses)."""
        config = self.zenoh()
        try:
            return zenoh.open(config)
        except zenoh.ZError as exc:
            raise BusError(f"cannot open the Zenoh session ({self.mode} via {self.where}): {exc}") from exc
