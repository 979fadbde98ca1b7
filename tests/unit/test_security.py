"""Security settings: what they render into a Zenoh config, what they refuse, how they travel by environment."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh
from pydantic import ValidationError

from protocol.keys import Keys
from services.bus.session import BusConfig
from services.bus.transport import session_config
from services.client import BusSettings, Security
from services.launcher.access import MESSAGES, access_control, read_access
from services.launcher.router import router_config


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    """Stand-ins for the PEM files and a password file (Security checks that they exist, not their contents)."""
    paths = {name: tmp_path / name for name in ("ca.pem", "cert.pem", "key.pem", "password")}
    for path in paths.values():
        path.write_text("x\n")
    paths["password"].write_text("s3cret\n")
    return paths


def rendered(config: zenoh.Config, key: str) -> object:
    return json.loads(config.get_json(key))


def test_tls_and_credentials_render_as_zenoh_entries(files):
    security = Security(root_ca=files["ca.pem"], cert=files["cert.pem"], key=files["key.pem"], mutual=True,
                        user="tracker", password_file=files["password"])
    config = session_config("client", connect=("tls/10.0.0.5:7447",), security=security)
    tls = rendered(config, "transport/link/tls")
    assert tls["root_ca_certificate"] == str(files["ca.pem"])
    assert tls["listen_certificate"] == tls["connect_certificate"] == str(files["cert.pem"])
    assert tls["listen_private_key"] == tls["connect_private_key"] == str(files["key.pem"])
    assert tls["enable_mtls"] is True
    assert rendered(config, "transport/auth/usrpwd/user") == "tracker"
    assert rendered(config, "transport/auth/usrpwd/password") == "s3cret"  # read from the file, stripped


def test_no_security_leaves_the_config_plain():
    tls = rendered(session_config("peer", security=Security()), "transport/link/tls")
    assert tls["root_ca_certificate"] is None and tls["enable_mtls"] is None
    assert rendered(session_config("peer"), "transport/auth/usrpwd/user") is None


def test_password_stays_out_of_the_repr(files):
    assert "hunter2" not in repr(Security(user="u", password="hunter2"))


@pytest.mark.parametrize(("given", "says"), [
    ({"cert": "cert.pem"}, "give both or neither"),
    ({"mutual": True, "cert": "cert.pem", "key": "key.pem"}, "mutual TLS needs"),
    ({"user": "u", "password": "p", "password_file": "password"}, "not both"),
    ({"user": "u"}, "needs both a user and a password"),
    ({"password": "p"}, "needs both a user and a password"),
    ({"root_ca": "missing.pem"}, "TLS root CA .*missing.pem does not exist"),
    ({"cert": ".", "key": "key.pem"}, "TLS certificate .* is not a file"),
])
def test_inconsistent_settings_are_refused(files, given, says):
    folder = files["ca.pem"].parent
    values = {k: folder / v if k in ("root_ca", "cert", "key", "password_file") else v for k, v in given.items()}
    with pytest.raises(ValidationError, match=says):
        Security(**values)


def test_credentials_in_peer_mode_are_refused():
    with pytest.raises(ValidationError, match="needs client mode"):
        BusSettings(mode="peer", connect=("tcp/10.0.0.5:7447",), security=Security(user="u", password="p"))
    assert BusSettings(mode="client", connect=("tcp/10.0.0.5:7447",), security=Security(user="u", password="p"))


def test_a_tls_endpoint_without_a_root_ca_is_refused_by_name():
    with pytest.raises(ValidationError, match=r"endpoint tls/10\.0\.0\.5:7447 is TLS: give the root CA"):
        BusSettings(mode="client", connect=("tls/10.0.0.5:7447",))
    with pytest.raises(ValueError, match=r"listening on tls/0\.0\.0\.0:7447 needs a TLS certificate"):
        session_config("router", listen=("tls/0.0.0.0:7447",), security=Security())


def test_security_travels_by_environment_and_back(files):
    env = {"ARTRACK_MODE": "client", "ARTRACK_CONNECT": "tls/10.0.0.5:7447",
           "ARTRACK_TLS_ROOT_CA": str(files["ca.pem"]), "ARTRACK_TLS_CERT": str(files["cert.pem"]),
           "ARTRACK_TLS_KEY": str(files["key.pem"]), "ARTRACK_TLS_MUTUAL": "1",
           "ARTRACK_USER": "tracker", "ARTRACK_PASSWORD_FILE": str(files["password"])}
    bus = BusConfig.from_env(env)
    assert bus.security == Security(root_ca=files["ca.pem"], cert=files["cert.pem"], key=files["key.pem"],
                                    mutual=True, user="tracker", password_file=files["password"])
    child = bus.to_env()
    assert child["ARTRACK_PASSWORD"] == "" and child["ARTRACK_PASSWORD_FILE"] == str(files["password"])
    assert "s3cret" not in child.values()  # the file's path travels, not the password
    assert BusConfig.from_env(child) == bus


def test_a_plain_password_round_trips_too():
    bus = BusSettings.from_env({"ARTRACK_MODE": "client", "ARTRACK_USER": "app", "ARTRACK_PASSWORD": "p"})
    assert BusSettings.from_env(bus.to_env()).security.secret() == "p"


def test_command_line_security_updates_the_environment_field_by_field(files):
    env = {"ARTRACK_MODE": "client", "ARTRACK_USER": "tracker", "ARTRACK_PASSWORD": "p"}
    bus = BusSettings.from_env(env, security={"root_ca": files["ca.pem"]})
    assert bus.security.user == "tracker" and bus.security.root_ca == files["ca.pem"]
    replaced = BusSettings.from_env(env, security=Security(root_ca=files["ca.pem"]))
    assert replaced.security.user is None


ACCESS = """
namespace = "site/lab1"
[pipeline]
users = ["tracker"]
common_names = ["tracker.lab"]
[app]
users = ["dashboard"]
"""


def test_access_file_becomes_default_deny_zenoh_access_control(tmp_path):
    path = tmp_path / "acl.toml"
    path.write_text(ACCESS)
    acl = access_control(read_access(path))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {rule["id"]: rule for rule in acl["rules"]}
    assert rules["pipeline"]["key_exprs"] == ["site/lab1/**"] and set(rules["pipeline"]["messages"]) == set(MESSAGES)
    app_rules = [rule for rule in acl["rules"] if rule["id"].startswith("app")]
    assert all(rule["permission"] == "allow" for rule in acl["rules"])
    writes = [rule for rule in app_rules if {"put", "delete"} & set(rule["messages"]) and "ingress" in rule["flows"]]
    assert writes == []  # an app never writes
    assert {"id": "pipeline-usernames", "usernames": ["tracker"]} in acl["subjects"]
    assert {"id": "pipeline-cert_common_names", "cert_common_names": ["tracker.lab"]} in acl["subjects"]
    policies = {policy["id"]: policy for policy in acl["policies"]}
    assert set(policies) == {"pipeline-usernames", "pipeline-cert_common_names", "app-usernames"}
    assert set(policies["app-usernames"]["rules"]) == {rule["id"] for rule in app_rules}
    config = zenoh.Config()
    config.insert_json5("access_control", json.dumps(acl))  # Zenoh accepts every field
    assert rendered(config, "access_control/default_permission") == "deny"


@pytest.mark.parametrize(("text", "says"), [
    ("[pipeline\n", "is not TOML"),
    ("[auditor]\nusers = ['x']\n", "auditor: Extra inputs are not permitted"),
    ("[pipeline]\nusers = ['x']\n[app]\nusers = ['x']\n", "user x cannot hold both roles"),
    ("namespace = 'a b'\n", "namespace 'a b' is not a valid key name"),
])
def test_bad_access_files_are_refused_naming_the_file(tmp_path, text, says):
    path = tmp_path / "acl.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=f"access file {path}.*{says}"):
        read_access(path)


def test_a_missing_access_file_is_named(tmp_path):
    with pytest.raises(ValueError, match="acl.toml: No such file"):
        read_access(tmp_path / "acl.toml")


def test_namespace_wide_patterns_match_every_rig():
    ns = Keys("ar", "rig7")
    assert zenoh.KeyExpr(ns.all_poses()).intersects(zenoh.KeyExpr(ns.pose("cam0/marker/3")))
    assert zenoh.KeyExpr(ns.all_calibrations()).intersects(zenoh.KeyExpr(ns.calibration("cam1")))
    assert zenoh.KeyExpr(ns.all_static_transforms()).intersects(zenoh.KeyExpr(ns.static_transforms("cap")))
    assert zenoh.KeyExpr(ns.all_clients()).intersects(zenoh.KeyExpr(ns.client("abc")))
    assert not zenoh.KeyExpr(ns.all_poses()).intersects(zenoh.KeyExpr(ns.markers("cam0")))


def test_security_is_written_over_a_zenoh_config_file(files, tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tls/10.0.0.5:7447"] } }')
    config = BusSettings(zenoh_config=path, security=Security(root_ca=files["ca.pem"])).zenoh()
    assert rendered(config, "transport/link/tls/root_ca_certificate") == str(files["ca.pem"])


def test_router_config_carries_users_and_access(files, tmp_path):
    users, acl = tmp_path / "users.txt", tmp_path / "acl.toml"
    users.write_text("tracker:secret\n")
    acl.write_text(ACCESS)
    config = router_config(("tls/127.0.0.1:7447",), (), None, users=users, access=acl,
                           security=Security(cert=files["cert.pem"], key=files["key.pem"]))
    assert rendered(config, "transport/auth/usrpwd/dictionary_file") == str(users)
    assert rendered(config, "access_control/enabled") is True
    assert rendered(config, "transport/link/tls/listen_certificate") == str(files["cert.pem"])
    with pytest.raises(ValueError, match=f"users file {tmp_path / 'nobody.txt'} does not exist"):
        router_config(("tcp/127.0.0.1:7447",), (), None, users=tmp_path / "nobody.txt")


def test_errors_never_show_the_password(files):
    with pytest.raises(ValidationError, match="needs client mode") as refused:
        BusSettings.from_env({"ARTRACK_USER": "u", "ARTRACK_PASSWORD": "hunter2"})
    assert "hunter2" not in str(refused.value)
    with pytest.raises(ValidationError, match="not both") as refused:
        Security(user="u", password="hunter2", password_file=files["password"])
    assert "hunter2" not in str(refused.value)
    with pytest.raises(ValidationError, match="needs client mode") as refused:  # credentials given as a plain dict
        BusSettings(mode="peer", security={"user": "u", "password": "hunter2"})
    assert "nter2" not in str(refused.value)
    with pytest.raises(ValidationError) as refused:  # the other values refused are still shown
        BusSettings(mode="router", security={"user": "u", "password": "hunter2"})
    assert "'router'" in str(refused.value) and "nter2" not in str(refused.value)
    assert [e["loc"] for e in refused.value.errors()] == [("mode",)]


def test_an_empty_password_file_is_refused_when_the_session_is_configured(files):
    files["password"].write_text("\n")
    bus = BusSettings(mode="client", security=Security(user="u", password_file=files["password"]))
    with pytest.raises(ValueError, match=f"password file {files['password']} is empty"):
        bus.zenoh()
