"""Security against real `artrack router` processes: TLS, user/password, access roles, mutual TLS.

Certificates come from the example's ``certs.sh`` (the ``openssl`` command line), made once per
module in a temporary folder; the access file is the example's ``acl.toml``.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from protocol.codec import encode
from services.bus.discovery import client_states
from services.bus.session import reachable
from services.client import BusError, BusSettings, Security, connect
from tests.conftest import free_port
from tests.integration.busprobe import make_message
from tests.integration.support import START_S, wait_live, wait_until

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(shutil.which("openssl") is None, reason="the openssl command is not installed")]

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "secure"
TRACKER, DASHBOARD = "tracker.artrack.lan", "dashboard.artrack.lan"
"""Client certificate common names that the example's acl.toml names."""
FORGED = b"forged by an app"
USERS = {"tracker": "pipeline-secret", "dashboard": "app-secret"}


class Pki:
    """The files of one test module: certificates, users file, password files and the access file."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.ca = folder / "ca.pem"
        self.users = folder / "users.txt"
        self.acl = EXAMPLE / "acl.toml"

    def cert(self, name: str) -> Path:
        return self.folder / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.folder / f"{name}.key"

    def password_file(self, user: str) -> Path:
        return self.folder / f"{user}.password"


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Pki:
    """A CA, the router's certificate for 127.0.0.1, two client certificates, users and password files."""
    pki = Pki(tmp_path_factory.mktemp("pki"))
    subprocess.run(["sh", str(EXAMPLE / "certs.sh"), str(pki.folder), "127.0.0.1", TRACKER, DASHBOARD],
                   check=True, capture_output=True, timeout=60)
    pki.users.write_text("".join(f"{user}:{password}\n" for user, password in USERS.items()))
    for user, password in USERS.items():
        pki.password_file(user).write_text(password + "\n")
    return pki


def start_router(procs, pki: Pki, *options: str) -> str:
    """`artrack router` on a free TLS endpoint with the router's certificate; returns the endpoint."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = procs.artrack("router", "--listen", endpoint, "--tls-cert", str(pki.cert("router")), "--tls-key",
                           str(pki.key("router")), "--tls-ca", str(pki.ca), *options, name="router")

    def up() -> bool:
        assert router.poll() is None, f"the router exited:\n{router.describe()}"
        return reachable(endpoint)

    wait_until(up, START_S, f"the router on {endpoint}")
    return endpoint


def settings(endpoint: str, bus, **security: object) -> BusSettings:
    return BusSettings(mode="client", connect=(endpoint,), rig=bus.rig, security=Security(**security))


def pose_reaches(sender, key: str, app, target: str):
    """Publish a pose on ``key`` from ``sender`` until ``app`` has it as its latest for ``target``."""
    payload = encode(make_message("pose", 1))

    def arrived():
        sender.put(key, payload)
        return app.latest(target, timeout_s=0.2)

    return wait_until(arrived, START_S, f"a pose on {key}")


def test_tls_router_serves_a_tls_client_and_refuses_plain_tcp(bus, procs, pki):
    endpoint = start_router(procs, pki)
    publisher = settings(endpoint, bus, root_ca=pki.ca).open()
    try:
        with connect(mode="client", connect=endpoint, rig=bus.rig, security=Security(root_ca=pki.ca)) as app:
            update = pose_reaches(publisher, bus.keys.pose("cam0/marker/1"), app, "cam0/marker/1")
            assert update.pose == make_message("pose", 1)
    finally:
        publisher.close()
    plain = endpoint.replace("tls/", "tcp/")
    with pytest.raises(BusError, match=re.escape(plain)):
        connect(mode="client", connect=plain, rig=bus.rig)


def test_router_refuses_a_wrong_or_missing_password(bus, procs, pki):
    endpoint = start_router(procs, pki, "--users", str(pki.users))
    password_file = pki.password_file("dashboard")
    settings(endpoint, bus, root_ca=pki.ca, user="dashboard", password_file=password_file).open().close()
    with pytest.raises(BusError, match=re.escape(endpoint)):
        settings(endpoint, bus, root_ca=pki.ca, user="dashboard", password="pipeline-secret").open()
    with pytest.raises(BusError, match=re.escape(endpoint)):
        settings(endpoint, bus, root_ca=pki.ca).open()


def secure_env(endpoint: str, pki: Pki, user: str) -> dict[str, str]:
    """The environment a node on the secure router runs with (the password travels as a file)."""
    return {"ARTRACK_MODE": "client", "ARTRACK_CONNECT": endpoint, "ARTRACK_TLS_ROOT_CA": str(pki.ca),
            "ARTRACK_USER": user, "ARTRACK_PASSWORD_FILE": str(pki.password_file(user))}


def collect_keys(session, key: str) -> list[str]:
    """Keys of the samples ``session`` receives on ``key`` from now on, ``FORGED`` ones marked."""
    seen: list[str] = []

    def on_sample(sample) -> None:
        forged = sample.payload.to_bytes() == FORGED
        seen.append(f"{'forged ' if forged else ''}{sample.key_expr}")

    session.declare_subscriber(key, on_sample)
    return seen


def answer_queries(session, key: str, seen: list[str]) -> None:
    """Answer queries on ``key`` from ``session``, each one noted in ``seen`` as ``query KEY``."""

    def on_query(query) -> None:
        seen.append(f"query {query.key_expr}")
        query.reply(query.key_expr, b"")

    session.declare_queryable(key, on_query)


def ask_after_the_puts(app, key: str, seen: list[str]) -> None:
    """Query ``key`` from ``app`` until a query reaches the session answering it (``answer_queries`` into
    ``seen``). The router deals with an app's messages in the order they came and forwards them in that
    order, so once a query made after the app's puts has come through, every one of those puts has come
    through before it or was dropped."""

    def reached() -> bool:
        app.session.get(key)
        return f"query {key}" in seen

    wait_until(reached, START_S, f"the app's query on {key}")


def test_app_role_reads_a_secure_pipeline_but_cannot_write_into_it(bus, procs, pki):
    endpoint = start_router(procs, pki, "--users", str(pki.users), "--acl", str(pki.acl))
    pipeline_file = EXAMPLE.parents[1] / "pipelines" / "marker.toml"
    up = procs.artrack("up", str(pipeline_file), "--rig", bus.rig, env=secure_env(endpoint, pki, "tracker"))
    pipeline = settings(endpoint, bus, root_ca=pki.ca, user="tracker", password=USERS["tracker"]).open()
    other = settings(endpoint, bus, root_ca=pki.ca, user="tracker", password=USERS["tracker"]).open()
    try:
        wait_live(pipeline, bus.keys, {"capture", "marker-cam0"}, (up,))
        seen = collect_keys(pipeline, bus.keys.everything())
        probe = bus.keys.state("probe")
        answer_queries(pipeline, probe, seen)
        credentials = Security(root_ca=pki.ca, user="dashboard", password_file=pki.password_file("dashboard"))
        with connect(mode="client", connect=endpoint, rig=bus.rig, app="dashboard", security=credentials) as app:
            with app.poses("cam0/**", idle_timeout_s=START_S) as stream:
                assert next(stream).target.startswith("cam0/marker/")
            assert {"capture", "marker-cam0"} <= {name for rig, name in app.services() if rig == bus.rig}
            assert {"capture", "marker-cam0"} <= {name for rig, name in app.status() if rig == bus.rig}
            assert app.calibration("cam0") is not None
            assert "cam0" in app.frames(timeout_s=START_S)  # the rig's static transforms, asked for
            assert (bus.rig, app.id) in client_states(pipeline, bus.keys, 2.0)  # `artrack status` sees the app
            forged = [bus.keys.pose("cam0/forged"), bus.keys.markers("cam0"), bus.keys.image("cam9")]
            genuine = bus.keys.pose("cam0/genuine")
            for _ in range(5):
                for key in forged:
                    app.session.put(key, FORGED)
                other.put(genuine, b"genuine")
                time.sleep(0.05)
            wait_until(lambda: genuine in seen, START_S, "the pipeline user's put")
            ask_after_the_puts(app, probe, seen)
            assert not [key for key in seen if key.startswith("forged")], "an app's put reached the pipeline"
        listed = procs.run("list", "--mode", "client", "--connect", endpoint, "--rig", bus.rig, "--tls-ca", str(pki.ca),
                           "--user", "tracker", "--password-file", str(pki.password_file("tracker")))
        assert listed.wait(0) == 0 and {"capture", "marker-cam0"} <= set(listed.stdout.split()), listed.describe()
        status = procs.run("status", "--check", "--json", "--mode", "client", "--connect", endpoint, "--rig", bus.rig,
                           "--tls-ca", str(pki.ca), "--user", "dashboard",
                           "--password-file", str(pki.password_file("dashboard")))
        assert status.wait(0) == 0, status.describe()  # an app user may ask for the pipeline's health
        names = {n["name"] for p in json.loads(status.stdout)["pipelines"] for n in p["nodes"]}
        assert names == {"capture", "marker-cam0"}
    finally:
        other.close()
        pipeline.close()


def test_mutual_tls_names_the_app_by_its_certificate(bus, procs, pki):
    endpoint = start_router(procs, pki, "--tls-mutual", "--acl", str(pki.acl))
    tracker_tls = {"root_ca": pki.ca, "cert": pki.cert(TRACKER), "key": pki.key(TRACKER), "mutual": True}
    pipeline = settings(endpoint, bus, **tracker_tls).open()
    other = settings(endpoint, bus, **tracker_tls).open()
    try:
        seen = collect_keys(pipeline, bus.keys.everything())
        probe = bus.keys.state("probe")
        answer_queries(pipeline, probe, seen)
        app_tls = Security(root_ca=pki.ca, cert=pki.cert(DASHBOARD), key=pki.key(DASHBOARD), mutual=True)
        with connect(mode="client", connect=endpoint, rig=bus.rig, security=app_tls) as app:
            pose_reaches(pipeline, bus.keys.pose("cam0/marker/2"), app, "cam0/marker/2")
            forged = bus.keys.pose("cam0/forged")
            for _ in range(5):
                app.session.put(forged, FORGED)
                other.put(bus.keys.pose("cam0/genuine"), b"genuine")
                time.sleep(0.05)
            wait_until(lambda: bus.keys.pose("cam0/genuine") in seen, START_S, "the pipeline certificate's put")
            ask_after_the_puts(app, probe, seen)
            assert f"forged {forged}" not in seen, "an app's put reached the pipeline"
    finally:
        other.close()
        pipeline.close()
    with pytest.raises(BusError, match=re.escape(endpoint)):
        settings(endpoint, bus, root_ca=pki.ca).open()
