"""Deployment with TLS: a router, server and trainer over TLS, mutual TLS, and strangers
(an unknown user, a certificate from another CA, expired certificates) refused and told why,
with the certificates scripts/make-certs.sh makes.

Every process is real (``python -m ...`` of the installed commands) on 127.0.0.1 with free
ports; each is ended by its PID, and every wait is on a condition with a deadline
(``tests.support.remote.wait_until``), never a fixed sleep.
"""

from __future__ import annotations

import secrets
import shutil
import subprocess
from pathlib import Path

import pytest

from overtake.client.wire.remote import Connection, RemoteConfig
from overtake.ipc.transport import SecurityConfig
from overtake.protocol import errors

from tests.support import deploy
from tests.support.remote import free_port

# Credentials in the developer's environment must not leak into these tests.
pytestmark = pytest.mark.usefixtures("no_inherited_credentials")


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA, a router certificate for localhost and 127.0.0.1, and a client certificate, made
    by the script the documentation tells users to run."""
    where = tmp_path_factory.mktemp("certs")
    done = subprocess.run(
        [
            "bash",
            str(deploy.ROOT / "scripts" / "make-certs.sh"),
            str(where),
            "localhost",
            deploy.LOOPBACK,
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return where


@pytest.mark.timeout(240)
def test_tls_router_with_server_and_trainer(tmp_path: Path, background, certificates: Path):
    ca = str(certificates / "ca.pem")
    port = free_port()
    deploy.start_router(
        background,
        "router",
        [f"tls/{deploy.LOOPBACK}:{port}"],
        "--tls-certificate",
        str(certificates / "router.pem"),
        "--tls-private-key",
        str(certificates / "router.key"),
    )
    server = deploy.start_server(
        background, "sim-tls", f"tls/{deploy.LOOPBACK}:{port}", "--tls-root-ca", ca
    )
    deploy.wait_for_server(
        "sim-tls",
        RemoteConfig(
            connect=(f"tls/{deploy.LOOPBACK}:{port}",),
            connect_timeout_s=10.0,
            security=SecurityConfig(tls_root_ca=Path(ca)),
        ),
        server,
    )

    # By name this time: the certificate names both localhost and 127.0.0.1.
    run_dir = tmp_path / "runs" / "dqn"
    done = deploy.run(
        deploy.train_argv("dqn", f"tls/localhost:{port}", run_dir, "--tls-root-ca", ca)
    )
    deploy.check_trained(done, run_dir)

    # The compose file's health check: exit 0 only when this very server answers.
    status = [
        deploy.PY,
        "-m",
        "overtake.client.wire.status",
        "--connect",
        f"tls/{deploy.LOOPBACK}:{port}",
        "--tls-root-ca",
        ca,
        "--timeout-s",
        "3",
        "--server",
    ]
    healthy = deploy.run([*status, "sim-tls"], timeout_s=60)
    assert healthy.returncode == 0 and "sim-tls: " in healthy.stdout, healthy
    assert deploy.run([*status, "sim-elsewhere"], timeout_s=60).returncode == 1
    # A client that does not trust the router's CA is refused, and told why.
    refused = deploy.run(
        [
            deploy.PY,
            "-m",
            "overtake.client.wire.status",
            "--connect",
            f"tls/{deploy.LOOPBACK}:{port}",
            "--timeout-s",
            "1",
        ],
        timeout_s=60,
    )
    assert refused.returncode != 0
    assert "is not trusted" in refused.stderr and "--tls-root-ca" in refused.stderr, refused.stderr
    # Plain TCP to a TLS listener.
    with pytest.raises(errors.ConnectError, match="is a TLS listener"):
        Connection(RemoteConfig(connect=(f"tcp/{deploy.LOOPBACK}:{port}",), connect_timeout_s=1.0))


@pytest.mark.timeout(120)
def test_mutual_tls_admits_only_clients_with_a_certificate(background, certificates: Path):
    ca, port = certificates / "ca.pem", free_port()
    endpoint = f"tls/{deploy.LOOPBACK}:{port}"
    deploy.start_router(
        background,
        "router-mtls",
        [endpoint],
        "--tls-root-ca",
        str(ca),
        "--tls-mtls",
        "--tls-certificate",
        str(certificates / "router.pem"),
        "--tls-private-key",
        str(certificates / "router.key"),
    )
    with_certificate = SecurityConfig(
        tls_root_ca=ca,
        tls_mtls=True,
        tls_certificate=certificates / "client.pem",
        tls_private_key=certificates / "client.key",
    )
    connection = Connection(
        RemoteConfig(connect=(endpoint,), connect_timeout_s=10.0, security=with_certificate)
    )
    try:
        assert connection.discover() == []  # admitted; no server on this network
    finally:
        connection.close()
    with pytest.raises(errors.ConnectError, match="requires a client certificate"):
        Connection(
            RemoteConfig(
                connect=(endpoint,), connect_timeout_s=1.0, security=SecurityConfig(tls_root_ca=ca)
            )
        )


def sign_with_dates(
    ca_dir: Path, name: str, usage: str, start: str, end: str, san: str | None = None
) -> Path:
    """A certificate ``name``.pem (and .key) signed by the CA in ``ca_dir``, valid from
    ``start`` to ``end`` (YYYYMMDDHHMMSSZ): ``openssl ca`` sets any dates, where OpenSSL 3.0's
    ``x509 -req`` only counts days from now. Returns the .pem."""
    work = ca_dir / f"{name}-ca"
    work.mkdir()
    (work / "index.txt").write_text("")
    (work / "serial").write_text(secrets.token_hex(8) + "\n")
    (work / "ca.cnf").write_text(
        "[ca]\ndefault_ca = local\n[local]\n"
        f"database = {work / 'index.txt'}\nserial = {work / 'serial'}\n"
        f"new_certs_dir = {work}\ndefault_md = sha256\npolicy = anything\n"
        "unique_subject = no\ncopy_extensions = none\n"
        "[anything]\ncommonName = supplied\n"
    )
    (work / "ext.cnf").write_text(
        "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        f"extendedKeyUsage={usage}\n" + (f"subjectAltName={san}\n" if san else "")
    )
    key, csr, pem = ca_dir / f"{name}.key", work / "req.csr", ca_dir / f"{name}.pem"
    for argv in (
        [
            "openssl",
            "req",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
            "-nodes",
            "-keyout",
            key,
            "-out",
            csr,
            "-subj",
            f"/CN={name}",
        ],
        [
            "openssl",
            "ca",
            "-batch",
            "-notext",
            "-config",
            work / "ca.cnf",
            "-cert",
            ca_dir / "ca.pem",
            "-keyfile",
            ca_dir / "ca.key",
            "-in",
            csr,
            "-out",
            pem,
            "-startdate",
            start,
            "-enddate",
            end,
            "-extfile",
            work / "ext.cnf",
        ],
    ):
        done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
    return pem


@pytest.mark.timeout(180)
def test_strangers_are_refused_and_told_why(tmp_path: Path, background, certificates: Path):
    # The strangers, each refused with words a user understands: an unknown user at
    # a usrpwd router; at a mutual-TLS router a client certificate from another CA and an
    # expired one; a router whose own certificate has expired.
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("trainer:trainer-secret\n")
    usrpwd_ep = f"tcp/{deploy.LOOPBACK}:{free_port()}"
    deploy.start_router(
        background, "router-usrpwd", [usrpwd_ep], "--credentials-file", str(credentials)
    )
    with pytest.raises(errors.ConnectError, match="or a user its credentials file does not list"):
        Connection(
            RemoteConfig(
                connect=(usrpwd_ep,),
                connect_timeout_s=1.0,
                security=SecurityConfig(user="mallory", password_file=credentials),
            )
        )

    ca = certificates / "ca.pem"
    other = tmp_path / "other-ca"
    made = subprocess.run(
        ["bash", str(deploy.ROOT / "scripts" / "make-certs.sh"), str(other)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    mtls_ep = f"tls/{deploy.LOOPBACK}:{free_port()}"
    deploy.start_router(
        background,
        "router-mtls",
        [mtls_ep],
        *("--tls-root-ca", str(ca), "--tls-mtls"),
        *("--tls-certificate", str(certificates / "router.pem")),
        *("--tls-private-key", str(certificates / "router.key")),
    )

    def mtls_client(certificate: Path) -> SecurityConfig:
        return SecurityConfig(
            tls_root_ca=ca,
            tls_mtls=True,
            tls_certificate=certificate,
            tls_private_key=certificate.with_suffix(".key"),
        )

    with pytest.raises(errors.ConnectError, match="is not signed by a CA it trusts"):
        Connection(
            RemoteConfig(
                connect=(mtls_ep,),
                connect_timeout_s=1.0,
                security=mtls_client(other / "client.pem"),
            )
        )
    # Signed by the right CA, expired in 2021.
    expired_dir = tmp_path / "expired"
    expired_dir.mkdir()
    for name in ("ca.pem", "ca.key"):
        shutil.copy(certificates / name, expired_dir / name)
    old_client = sign_with_dates(
        expired_dir, "old-client", "clientAuth", "20200101000000Z", "20210101000000Z"
    )
    with pytest.raises(
        errors.ConnectError, match="refused this side's certificate: it has expired"
    ):
        Connection(
            RemoteConfig(
                connect=(mtls_ep,), connect_timeout_s=1.0, security=mtls_client(old_client)
            )
        )

    old_router = sign_with_dates(
        expired_dir,
        "old-router",
        "serverAuth,clientAuth",
        "20200101000000Z",
        "20210101000000Z",
        san=f"IP:{deploy.LOOPBACK},DNS:localhost",
    )
    stale_ep = f"tls/{deploy.LOOPBACK}:{free_port()}"
    deploy.start_router(
        background,
        "router-expired",
        [stale_ep],
        *("--tls-certificate", str(old_router)),
        *("--tls-private-key", str(old_router.with_suffix(".key"))),
    )
    with pytest.raises(errors.ConnectError, match="has expired") as refused:
        Connection(
            RemoteConfig(
                connect=(stale_ep,),
                connect_timeout_s=1.0,
                security=SecurityConfig(tls_root_ca=ca),
            )
        )
    assert "scripts/make-certs.sh" in str(refused.value)
