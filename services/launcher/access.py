"""Who may do what on the router: a small TOML access file turned into Zenoh's ``access_control``.

::

    namespace = "ar"                       # whose keys (default "ar")

    [pipeline]                             # capture, trackers, recorder, viewer, artrack status
    users = ["tracker"]                    # user names of the router's users file
    common_names = ["tracker.lab"]         # and/or certificate common names (mutual TLS)

    [app]                                  # client apps
    users = ["dashboard"]

Roles, as seen by the router (ingress: from that session; egress: to it):

* ``pipeline``: every message, both ways, on every key of the namespace;
* ``app``: subscribes to poses and receives them; watches and queries node liveliness; queries
  node state, pipeline health (``artrack status``), camera calibration and the rig's static
  transforms and receives the replies; holds its own client token and answers its own state queryable (so ``artrack
  status`` lists it). Nothing else: its puts and deletes on the pipeline's keys are dropped at
  the router.

Everything not allowed is denied, including every session that matches no subject. Zenoh's
own access control enforces this (in the router, so apps and nodes connect in client mode).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator, model_validator

from protocol.keys import Keys, check_name

INGRESS, EGRESS = "ingress", "egress"
MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
            "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")
"""Every message kind Zenoh 1.10's access control filters."""


class Members(BaseModel):
    """The sessions that hold one role: by user name and/or by certificate common name."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    users: tuple[str, ...] = ()
    common_names: tuple[str, ...] = ()

    @property
    def names(self) -> set[str]:
        return {*(f"user {u}" for u in self.users), *(f"certificate {c}" for c in self.common_names)}


class Access(BaseModel):
    """The access file (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    namespace: str = "ar"
    pipeline: Members = Members()
    app: Members = Members()

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        return check_name(value, "namespace", segments=True)

    @model_validator(mode="after")
    def _one_role_each(self) -> Access:
        both = self.pipeline.names & self.app.names
        if both:
            raise ValueError(f"{', '.join(sorted(both))} cannot hold both roles")
        return self


def read_access(path: Path) -> Access:
    """The access file at ``path``; ValueError naming the file and the problem."""
    try:
        return Access.model_validate(tomllib.loads(path.read_text()))
    except OSError as exc:
        raise ValueError(f"access file {path}: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"access file {path} is not TOML: {exc}") from exc
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'file'}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"access file {path}: {problems}") from exc


def _rule(rule_id: str, messages: tuple[str, ...], flows: tuple[str, ...], *key_exprs: str) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "messages": list(messages), "flows": list(flows),
            "key_exprs": list(key_exprs)}


def _rules(keys: Keys) -> dict[str, list[dict[str, Any]]]:
    """Rule lists of each role, for the namespace of ``keys``."""
    watch = ("declare_liveliness_subscriber", "liveliness_query")
    status = (keys.all_states(), keys.all_supervisors(), keys.all_calibrations(), keys.all_static_transforms(),
              keys.all_client_states())
    return {
        "pipeline": [_rule("pipeline", MESSAGES, (INGRESS, EGRESS), keys.whole_namespace())],
        "app": [
            _rule("app-poses-ask", ("declare_subscriber",), (INGRESS,), keys.all_poses()),
            _rule("app-poses-get", ("put",), (EGRESS,), keys.all_poses()),
            _rule("app-nodes-watch", watch, (INGRESS,), keys.all_nodes(), keys.all_clients()),
            _rule("app-nodes-get", ("liveliness_token",), (EGRESS,), keys.all_nodes(), keys.all_clients()),
            _rule("app-queries-ask", ("query",), (INGRESS,), *status),
            _rule("app-queries-get", ("reply",), (EGRESS,), *status),
            _rule("app-own-token", ("liveliness_token",), (INGRESS,), keys.all_clients()),
            _rule("app-own-state", ("declare_queryable", "reply"), (INGRESS,), keys.all_client_states()),
            _rule("app-own-state-asked", ("query",), (EGRESS,), keys.all_client_states()),
        ],
    }


def access_control(access: Access) -> dict[str, Any]:
    """Zenoh's ``access_control`` config for ``access``: default deny, one policy per role and kind of subject."""
    rules_by_role = _rules(Keys(access.namespace))
    rules, subjects, policies = [], [], []
    for role, members in (("pipeline", access.pipeline), ("app", access.app)):
        role_rules = rules_by_role[role]
        rules += role_rules
        for kind, names in (("usernames", members.users), ("cert_common_names", members.common_names)):
            if names:
                subject = f"{role}-{kind}"
                subjects.append({"id": subject, kind: list(names)})
                policies.append({"id": subject, "rules": [r["id"] for r in role_rules], "subjects": [subject]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
