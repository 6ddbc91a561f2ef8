"""`training-server kit`: everything a real deployment needs, generated, for N robots and any fleet.

    training-server kit --out KIT --host server.fleet.example [--host 10.0.0.2 ...] --robots r1,r2,r3,r4
                        [--fleet default] [--map-args "--env museum"] [--data-dir /var/lib/mures]
                        [--http-port 8000] [--zenoh-port 7447] [--backend MODULE:CLASS]

Run it on the server machine (it issues the robots' credentials into the server's data directory,
as `training-server robots add` does). It writes::

    KIT/ca/ca.pem, ca-key.pem            the fleet's certificate authority (made once, then reused:
                                          run the kit again to add robots under the same CA)
    KIT/server/                          copy to /etc/mures/server/ on the server
        server.env                       the settings deploy/systemd/mures-training-server.service reads
        tls/server.pem, server-key.pem   the server's certificate (every --host as a name) and key
        tls/ca.pem                       the CA certificate
        zenohd/router.json5, users.txt   for a zenohd router instead of the server's own (TLS, one user
                                          per robot and one for the server, access control for all robots)
        zenohd/server-client.json5       the server's client configuration for that router
    KIT/robots/<id>/                     copy to /etc/mures/robot/ on robot <id>
        robot.env                        the settings deploy/systemd/mures-robot-agent.service reads
        token, zenoh-password, ca.pem    its HTTP token (scoped to it), Zenoh password, the CA
    KIT/operators/ca.pem                 what operators' browsers must trust (docs: docs/deploying.md)
    KIT/world/                           with --world: a simulated world's Zenoh password, the CA and
                                          world.env, for `mures world` to fly --backend sim robots
                                          through the secured router (docs/deploying.md)

Every robot named gets a bundle. A robot whose bundle is already in KIT keeps its credentials (its
secrets are not rewritten; its settings are) unless ``--reissue`` is given; a robot that holds
credentials but has no bundle here (issued by `training-server robots add`, or a bundle deleted)
is issued new ones, since the server keeps only a hash of its token: the old ones stop working.
Values in the .env files are double-quoted where they hold spaces, so that both systemd's
EnvironmentFile= and a shell's ``source`` read them. Secrets are written with mode 0600.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import shlex
from pathlib import Path
from typing import Any

import training_server.credentials as credentials
from shared.core.files import write_private
from shared.core.wire import DEFAULT_FLEET, check_id

SERVER_ETC = "/etc/mures/server"  # where KIT/server/ is installed on the server
ROBOT_ETC = "/etc/mures/robot"  # where KIT/robots/<id>/ is installed on each robot
CERT_DAYS = 825  # the longest validity browsers accept for a server certificate


def _key() -> Any:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _pem_key(key: Any) -> str:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ).decode()


def _pem_cert(cert: Any) -> str:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM).decode()


def ensure_ca(ca_dir: Path, fleet: str, days: int) -> tuple[Any, Any]:
    """The fleet's CA (certificate, key): read from ``ca_dir`` if there, else made (a CA of its own,
    so that Zenoh's rustls accepts the server's certificate, which it signs)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    cert_path, key_path = ca_dir / "ca.pem", ca_dir / "ca-key.pem"
    if cert_path.exists() and key_path.exists():
        from cryptography.hazmat.primitives import serialization

        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        return cert, key
    key = _key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"MuRES fleet {fleet} CA")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    ca_dir.mkdir(parents=True, exist_ok=True)
    write_private(key_path, _pem_key(key))
    cert_path.write_text(_pem_cert(cert), encoding="utf-8")
    return cert, key


def server_certificate(ca: tuple[Any, Any], hosts: list[str], days: int) -> tuple[str, str]:
    """(certificate PEM, key PEM) for the server, every host (a DNS name or an IP address) in its
    subject alternative names, signed by the CA."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    ca_cert, ca_key = ca
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    key = _key()
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return _pem_cert(cert), _pem_key(key)


def _env(path: Path, values: dict[str, str], header: str) -> None:
    """An environment file for systemd's EnvironmentFile= (and docker compose's env_file)."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    lines += [f"{k}={_env_value(v)}" for k, v in values.items()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _env_value(value: str) -> str:
    """A value as systemd's EnvironmentFile= and a POSIX shell both read it back: bare when it is
    plain, else in double quotes (with \\, \", $ and ` escaped)."""
    if value and all(c.isalnum() or c in "-_./:,@+=%" for c in value):
        return value
    for c in '\\"$`':
        value = value.replace(c, "\\" + c)
    return f'"{value}"'


def zenohd_config(fleet: str, robot_ids: list[str], port: int, world: bool = False) -> dict[str, Any]:
    """A zenohd configuration (JSON, which JSON5 reads): TLS listener, user/password authentication,
    and the server's generated access control for ``robot_ids`` plus a ``server`` user that may use
    every key of the fleet."""
    acl = credentials.access_control(fleet, robot_ids, world=world)
    acl["rules"].insert(
        0,
        {
            "id": "server",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": [
                "put",
                "delete",
                "query",
                "reply",
                "declare_subscriber",
                "declare_queryable",
                "liveliness_token",
                "liveliness_query",
                "declare_liveliness_subscriber",
            ],
            "key_exprs": [f"mures/{fleet}/**"],
        },
    )
    acl["subjects"].insert(0, {"id": "server", "usernames": ["server"]})
    acl["policies"].insert(0, {"rules": ["server"], "subjects": ["server"]})
    return {
        "mode": "router",
        "listen": {"endpoints": [f"tls/0.0.0.0:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "listen_certificate": f"{SERVER_ETC}/tls/server.pem",
                    "listen_private_key": f"{SERVER_ETC}/tls/server-key.pem",
                }
            },
            "auth": {"usrpwd": {"dictionary_file": f"{SERVER_ETC}/zenohd/users.txt"}},
        },
        "access_control": acl,
    }


def build_kit(args: argparse.Namespace) -> dict[str, Any]:
    """Write the kit (module docstring); returns what was written, for the summary."""
    import secrets

    fleet = check_id("fleet", args.fleet)
    robots = [check_id("robot id", r) for r in args.robots.split(",") if r]
    if credentials.WORLD_USER in robots:
        raise ValueError(f"robot id {credentials.WORLD_USER!r} is the simulated world's Zenoh user; name it otherwise")
    if not robots:
        raise ValueError("--robots must name at least one robot (r1,r2,...)")
    if len(set(robots)) != len(robots):
        raise ValueError("--robots names a robot twice")
    hosts = list(dict.fromkeys(args.host))
    out, data = Path(args.out), Path(args.data_dir)
    data.mkdir(parents=True, exist_ok=True)
    ca = ensure_ca(out / "ca", fleet, args.days)
    ca_pem = (out / "ca" / "ca.pem").read_text(encoding="utf-8")
    host = hosts[0]

    # the server
    srv = out / "server"
    (srv / "tls").mkdir(parents=True, exist_ok=True)
    cert, key = server_certificate(ca, hosts, args.days)
    (srv / "tls" / "server.pem").write_text(cert, encoding="utf-8")
    write_private(srv / "tls" / "server-key.pem", key)
    (srv / "tls" / "ca.pem").write_text(ca_pem, encoding="utf-8")
    _env(
        srv / "server.env",
        {
            "MURES_MAP_ARGS": args.map_args,
            "MURES_FLEET": fleet,
            "MURES_DATA_DIR": str(data),
            "MURES_HTTP": f"0.0.0.0:{args.http_port}",
            "MURES_SERVER_DIR": SERVER_ETC,
            "MURES_ZENOH_LISTEN": f"tls/0.0.0.0:{args.zenoh_port}",
        },
        f"training-server settings for fleet {fleet!r} (deploy/systemd/mures-training-server.service).\n"
        f"Install: copy this directory to {SERVER_ETC}/ on the server; the data directory holds the\n"
        "robots' credentials, the database and the policies.",
    )

    # the robots: credentials into the server's data directory, a bundle each
    issued, kept, replaced = [], [], []
    have = credentials.robots(data)
    for r in robots:
        bundle = out / "robots" / r
        has_bundle = (bundle / "token").is_file() and (bundle / "zenoh-password").is_file()
        if r in have and has_bundle and not args.reissue:
            kept.append(r)
        else:
            if r in have and not has_bundle and not args.reissue:
                replaced.append(r)  # its token exists only as a hash: it cannot be written into a bundle
            token, password = credentials.issue(data, r)
            bundle.mkdir(parents=True, exist_ok=True)
            write_private(bundle / "token", token + "\n")
            write_private(bundle / "zenoh-password", password + "\n")
            issued.append(r)
        (bundle / "ca.pem").write_text(ca_pem, encoding="utf-8")
        _env(
            bundle / "robot.env",
            {
                "MURES_ROBOT_ID": r,
                "MURES_FLEET": fleet,
                "MURES_SERVER_URL": f"https://{_url_host(host)}:{args.http_port}",
                "MURES_ZENOH_CONNECT": f"tls/{_url_host(host)}:{args.zenoh_port}",
                "MURES_ROBOT_DIR": ROBOT_ETC,
                "MURES_BACKEND": args.backend,
                "MURES_BACKEND_ARGS": "",
            },
            f"robot-agent settings of robot {r} (deploy/systemd/mures-robot-agent.service).\n"
            f"Install: copy this directory to {ROBOT_ETC}/ on the robot (token and zenoh-password\n"
            "are secrets: mode 0600, owned by the user the agent runs as). MURES_BACKEND: your robot's\n"
            "backend (robot_agent/backend.py); sim flies in `mures world`'s simulated building, nav2 a\n"
            "Nav2 robot; MURES_BACKEND_ARGS: its flags, split at spaces (e.g. --nav2-connect\n"
            "tcp/127.0.0.1:7447 --nav2-regions /etc/mures/robot/regions.png --nav2-map /etc/mures/robot/map.yaml).",
        )

    # a simulated world, for flying --backend sim robots through the secured router
    if args.world:
        world_dir = out / "world"
        world_dir.mkdir(parents=True, exist_ok=True)
        if credentials.world_password(data) is None or not (world_dir / "zenoh-password").is_file():
            write_private(world_dir / "zenoh-password", credentials.issue_world(data) + "\n")
        (world_dir / "ca.pem").write_text(ca_pem, encoding="utf-8")
        _env(
            world_dir / "world.env",
            {
                "MURES_FLEET": fleet,
                "MURES_MAP_ARGS": args.map_args,
                "MURES_ZENOH_CONNECT": f"tls/{_url_host(host)}:{args.zenoh_port}",
            },
            "a simulated world for robots flown with --backend sim (docs/deploying.md):\n"
            "mures world $MURES_MAP_ARGS --fleet $MURES_FLEET --zenoh-connect $MURES_ZENOH_CONNECT \\\n"
            "  --zenoh-ca ca.pem --zenoh-user world --zenoh-password-file zenoh-password",
        )
    world = credentials.world_password(data) is not None

    # zenohd, for a router that is not the server's own
    every = sorted(credentials.robots(data))
    (srv / "zenohd").mkdir(exist_ok=True)
    (srv / "zenohd" / "router.json5").write_text(
        "// generated by training-server kit: zenohd -c /etc/mures/server/zenohd/router.json5\n"
        + json.dumps(zenohd_config(fleet, every, args.zenoh_port, world=world), indent=2)
        + "\n",
        encoding="utf-8",
    )
    server_password = secrets.token_urlsafe(24)
    users = [f"server:{server_password}"] + [f"{r}:{credentials.robots(data)[r]['zenoh_password']}" for r in every]
    if world:
        users.append(f"{credentials.WORLD_USER}:{credentials.world_password(data)}")
    write_private(srv / "zenohd" / "users.txt", "\n".join(users) + "\n")
    (srv / "zenohd" / "server-client.json5").write_text(
        json.dumps(
            {
                "mode": "client",
                "connect": {"endpoints": [f"tls/{_url_host(host)}:{args.zenoh_port}"]},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {
                    "link": {"tls": {"root_ca_certificate": f"{SERVER_ETC}/tls/ca.pem"}},
                    "auth": {"usrpwd": {"user": "server", "password": server_password}},
                },
            },
            indent=2,
        )
        + "\n",
        encoding="utf-8",
    )
    (srv / "zenohd" / "server-client.json5").chmod(0o600)
    (out / "operators").mkdir(exist_ok=True)
    (out / "operators" / "ca.pem").write_text(ca_pem, encoding="utf-8")
    return {
        "issued": issued,
        "kept": kept,
        "replaced": replaced,
        "robots_with_credentials": every,
        "hosts": hosts,
        "out": str(out),
        "server_running": server_running(data),
    }


def server_running(data_dir: Path) -> bool:
    """Whether a training-server holds ``data_dir`` now (its lock on server.lock)."""
    import fcntl

    lock = data_dir / "server.lock"
    if not lock.exists():
        return False
    with open(lock, "a+", encoding="utf-8") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    return False


def _url_host(host: str) -> str:
    """A host as it stands in a URL or a Zenoh endpoint (an IPv6 address in brackets)."""
    try:
        return f"[{host}]" if ipaddress.ip_address(host).version == 6 else host
    except ValueError:
        return host


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="training-server kit",
        description="the files a deployment needs: the fleet's CA, the server's certificate and settings, "
        "zenohd's users and access control, and each robot's install bundle",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="where to write the kit")
    p.add_argument(
        "--host",
        action="append",
        required=True,
        help="the server's name or address as robots and browsers reach it (repeatable; the first is used in "
        "the robots' settings, all are in the certificate)",
    )
    p.add_argument("--robots", required=True, help="robot ids, comma-separated (r1,r2,r3,r4)")
    p.add_argument("--fleet", default=DEFAULT_FLEET, help="fleet name (default 'default')")
    p.add_argument("--map-args", default="--env museum", help="the server's map (default '--env museum')")
    p.add_argument("--data-dir", default="/var/lib/mures", help="the server's data directory (default /var/lib/mures)")
    p.add_argument("--http-port", type=int, default=8000)
    p.add_argument("--zenoh-port", type=int, default=7447)
    p.add_argument(
        "--backend",
        default="robot_agent.examples.nav_goal:NavGoalBackend",
        help="the robots' backend (MODULE:CLASS, or sim); the default is the adapter to subclass, which refuses "
        "to start as it is",
    )
    p.add_argument("--days", type=int, default=CERT_DAYS, help=f"certificates' validity (default {CERT_DAYS})")
    p.add_argument("--reissue", action="store_true", help="new credentials for robots that have them already")
    p.add_argument(
        "--world",
        action="store_true",
        help="also credentials for a simulated world (KIT/world/), so that `mures world` can fly robots whose backend "
        "is sim through the secured router",
    )
    return p


def kit_main(argv: list[str]) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    if not 0 < args.http_port < 65536 or not 0 < args.zenoh_port < 65536:
        p.error("--http-port and --zenoh-port must be ports (1-65535)")
    if args.days < 1:
        p.error("--days must be at least 1")
    try:
        shlex.split(args.map_args)
        done = build_kit(args)
    except (ValueError, OSError) as exc:
        print(f"training-server kit: error: {exc}", file=__import__("sys").stderr)
        return 2
    taken = (
        "the running server takes the change within seconds (no restart)"
        if done["server_running"]
        else f"no server runs on {args.data_dir} now: start it (docs/deploying.md) and it reads them"
    )
    print(
        f"kit in {done['out']}: CA, server certificate for {', '.join(done['hosts'])}, "
        f"bundles for {', '.join(sorted(done['issued'] + done['kept']))}"
        + (f" (new credentials for {', '.join(done['issued'])})" if done["issued"] else "")
        + (f"; kept the credentials of {', '.join(done['kept'])} (--reissue for new ones)" if done["kept"] else "")
        + (
            f"; {', '.join(done['replaced'])} held credentials from `robots add`, which the kit cannot read back: "
            "replaced (the old ones no longer work)"
            if done["replaced"]
            else ""
        )
        + f". {len(done['robots_with_credentials'])} robots hold credentials; {taken}."
    )
    return 0
