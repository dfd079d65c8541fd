"""The deployment's local certificate authority: one CA, one X.509 certificate per service identity,
and the coordinator's Ed25519 plan-signing key (`rmmdet pki init`).

Layout of a PKI directory (default `.run/pki`, private keys mode 0600):

    ca.pem, ca.key                 the CA (ECDSA P-256, self-signed, path length 0)
    <identity>.pem, <identity>.key one leaf per identity: CN = identity, SAN = DNS:identity; a
                                   router's also its own loopback address (`router_loopback`) and
                                   its extra names,
                                   with serverAuth + clientAuth (routers listen and connect); every
                                   other identity's clientAuth only (it connects, never serves: a
                                   stolen sensor key cannot pose as the router while it restarts)
    plan-signing.key / .pub        Ed25519, PKCS#8 / SubjectPublicKeyInfo PEM
    plan-signing.next.key / .pub   the staged next plan key during a rotation (`rotate_plan_key`)
    plan-signing.region<k>.key/.pub  shard k's own plan key (`coordinator-region<k>`): each shard signs
                                   its plans, cliques and handovers with it, and a vehicle takes a
                                   pushed plan only from the key of the shard that answered it last
    generations.json               identity -> how many times its leaf was revoked (`revoke`): the
                                   leaf's CN is `<identity>.<generation>` after the first revocation
    retired/<UTC time>/            public halves of rotated-out CAs and plan keys (`rotate_ca`)

Zenoh's TLS links (rustls) verify chains to `ca.pem`; access control keys its rules on the leaf's
common name (`shared/security/acl.py`). Zenoh's TLS has no revocation lists, so one leaf is revoked by
reissuing it under a new common name (`revoke`): the routers' access control, rendered again, names
only the current one, and the old certificate may connect but do nothing (default deny).
`init` is idempotent: what exists is kept, what is missing is made, so adding an identity never
reissues the others (their keys may already be on other hosts).
"""

from __future__ import annotations

import datetime as dt
import errno
import ipaddress
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from shared.config import ConfigError
from shared.security.identities import is_router, router_loopback, shard_region

CA_NAME = "ca"
PLAN_KEY_NAME = "plan-signing"
NEXT_PLAN_KEY_NAME = f"{PLAN_KEY_NAME}.next"
RETIRED_DIR = "retired"  # public halves of rotated-out CAs and plan keys, by UTC time of rotation
GENERATIONS_FILE = "generations.json"  # identity -> revocations so far (`revoke`); public
CA_VALIDITY_DAYS = 3650
#: Leaves are short-lived (issue 34, item 3: a leaf that lived 825 days outlived any compromise of its
#: host): renew with `rmmdet pki init --renew` (the site launcher warns `RENEW_WITHIN_DAYS` ahead and
#: refuses an expired one); revoke at once by rotating the CA (`rotate_ca`).
LEAF_VALIDITY_DAYS = 90
RENEW_WITHIN_DAYS = 14
#: Identities are file names and certificate CNs: keep them to a safe alphabet.
IDENTITY_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
PRIVATE_MODE = 0o600
PUBLIC_MODE = 0o644  # certificates: anyone may read them


@dataclass(frozen=True)
class Paths:
    """Where one identity's files live in a PKI directory."""

    cert: Path
    key: Path


def identity_paths(pki_dir: Path, identity: str) -> Paths:
    check_identity(identity)
    return Paths(pki_dir / f"{identity}.pem", pki_dir / f"{identity}.key")


def ca_paths(pki_dir: Path) -> Paths:
    """The CA's certificate (every host has it) and private key (only where certificates are made)."""
    return Paths(pki_dir / f"{CA_NAME}.pem", pki_dir / f"{CA_NAME}.key")


def plan_key_paths(pki_dir: Path, name: str = PLAN_KEY_NAME) -> Paths:
    """The plan-signing key pair: `cert` is the public key (PEM), `key` the private key; `name`
    `NEXT_PLAN_KEY_NAME` for the staged next one."""
    return Paths(pki_dir / f"{name}.pub", pki_dir / f"{name}.key")


def shard_plan_key_name(region: int) -> str:
    """The plan key of the shard of region `region` (`plan_key_paths(pki_dir, name)`)."""
    return shard_key_path(Path(PLAN_KEY_NAME + ".key"), region).stem


def shard_key_path(key_path: Path, region: int) -> Path:
    """The key file shard `region` uses where the coordinator's is `key_path` (either half): beside
    it, `region<k>` before the suffix (`plan-signing.key` -> `plan-signing.region0.key`)."""
    return key_path.with_name(f"{key_path.stem}.region{region}{key_path.suffix}")


def next_key_name(name: str) -> str:
    """The staged successor of plan key `name` during a rotation."""
    return f"{name}.next"


def signer_name(public_key_path: Path) -> str:
    """Which signer a trusted public key file belongs to: its name without `.pub` and without `.next`
    (a staged key signs for the same coordinator or shard as the current one)."""
    return public_key_path.name.removesuffix(".pub").removesuffix(".next")


def trusted_plan_keys(pki_dir: Path) -> list[Path]:
    """The public keys vehicles trust: the coordinator's current plan key, each shard's
    (`shard_plan_key_name`), and any next one staged (`rotate_plan_key`), so plans signed by either
    verify while the signer switches over."""
    staged = plan_key_paths(pki_dir, NEXT_PLAN_KEY_NAME).cert
    shards = sorted(pki_dir.glob(f"{PLAN_KEY_NAME}.region*.pub"))
    return [plan_key_paths(pki_dir).cert, *([staged] if staged.exists() else []), *shards]


def generations(pki_dir: Path) -> dict[str, int]:
    """How many times each identity's leaf was revoked (absent: never). ConfigError when unreadable."""
    path = pki_dir / GENERATIONS_FILE
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: unreadable ({err})") from None
    if not isinstance(data, dict) or not all(
        isinstance(k, str) and type(v) is int and v >= 0 for k, v in data.items()
    ):
        raise ConfigError(f"{path}: expected {{identity: non-negative integer}}")
    return data


def certificate_name(identity: str, generation: int = 0) -> str:
    """The common name of `identity`'s leaf after `generation` revocations: the identity itself, then
    `<identity>.<generation>` (a dot is outside the identity alphabet, so no identity's name is another's
    revoked one)."""
    return identity if generation == 0 else f"{identity}.{generation}"


def current_common_names(pki_dir: Path) -> dict[str, str]:
    """identity -> the common name its current leaf has, for every identity ever revoked (the others:
    the identity itself)."""
    return {i: certificate_name(i, g) for i, g in generations(pki_dir).items()}


def check_identity(identity: str) -> str:
    if not IDENTITY_RE.match(identity) or identity in (CA_NAME, PLAN_KEY_NAME, RETIRED_DIR):
        raise ConfigError(f"identity {identity!r}: use 1-63 of [a-z0-9_-], not 'ca' or 'plan-signing'")
    return identity


def write_file(path: Path, data: bytes, mode: int) -> None:
    """Write `data` to `path` with exactly `mode`, also when the file was there with a wider one (a
    creation mode applies to new files only); a symbolic link at `path` is refused (O_NOFOLLOW), not
    followed to wherever it points. ConfigError when it cannot be written."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, mode)
    except OSError as exc:
        why = "a symbolic link, refused" if exc.errno == errno.ELOOP else exc.strerror
        raise ConfigError(f"{path}: cannot be written ({why})") from None
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), mode)
        f.write(data)


def _write_private(path: Path, pem: bytes) -> None:
    write_file(path, pem, PRIVATE_MODE)


def _key_pem(key: ec.EllipticCurvePrivateKey | Ed25519PrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "RMMDet deployment"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _key_usage(ca: bool) -> x509.KeyUsage:
    """Signatures only (ECDSA keys agree on TLS keys by signing); a CA also signs certificates."""
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class CertificateAuthority:
    """A CA certificate and its key, loaded from or created in a PKI directory."""

    def __init__(self, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> None:
        self.cert = cert
        self.key = key

    @classmethod
    def create(cls, pki_dir: Path, name: str = "RMMDet local CA") -> CertificateAuthority:
        key = ec.generate_private_key(ec.SECP256R1())
        now = _now()
        ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(name))
            .issuer_name(_name(name))
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=CA_VALIDITY_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(_key_usage(ca=True), critical=True)
            .add_extension(ski, critical=False)
            .sign(key, hashes.SHA256())
        )
        pki_dir.mkdir(parents=True, exist_ok=True)
        _write_private(ca_paths(pki_dir).key, _key_pem(key))
        write_file(ca_paths(pki_dir).cert, cert.public_bytes(serialization.Encoding.PEM), PUBLIC_MODE)
        return cls(cert, key)

    @classmethod
    def load(cls, pki_dir: Path) -> CertificateAuthority:
        try:
            cert = x509.load_pem_x509_certificate(ca_paths(pki_dir).cert.read_bytes())
            key = serialization.load_pem_private_key(ca_paths(pki_dir).key.read_bytes(), None)
        except (OSError, ValueError) as err:
            raise ConfigError(f"{pki_dir}: cannot load the CA: {err}") from None
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise ConfigError(f"{ca_paths(pki_dir).key}: expected an EC key, got {type(key).__name__}")
        return cls(cert, key)

    def issue(self, pki_dir: Path, identity: str, extra_names: tuple[str, ...] = ()) -> Paths:
        """Create `identity`'s key and certificate, signed by this CA. Only a router's certificate
        names addresses and may serve TLS; `extra_names` (addresses or DNS names) are a router's."""
        serves = is_router(identity)
        if extra_names and not serves:
            raise ConfigError(f"{identity}: only a router listens; extra names {extra_names} are a router's")
        paths = identity_paths(pki_dir, identity)
        key = ec.generate_private_key(ec.SECP256R1())
        now = _now()
        names: list[x509.GeneralName] = [x509.DNSName(identity)]
        if serves:
            addresses = {ipaddress.ip_address(router_loopback(identity))}
            for extra in extra_names:
                try:
                    addresses.add(ipaddress.ip_address(extra))
                except ValueError:
                    names.append(x509.DNSName(extra))
            names += [x509.IPAddress(a) for a in sorted(addresses, key=str)]
        usages = (
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            if serves
            else [ExtendedKeyUsageOID.CLIENT_AUTH]
        )
        ca_ski = self.cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
        cn = certificate_name(identity, generations(pki_dir).get(identity, 0))
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(cn))
            .issuer_name(self.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=LEAF_VALIDITY_DAYS))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(_key_usage(ca=False), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(usages),
                critical=False,
            )
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False
            )
            .sign(self.key, hashes.SHA256())
        )
        _write_private(paths.key, _key_pem(key))
        write_file(paths.cert, cert.public_bytes(serialization.Encoding.PEM), PUBLIC_MODE)
        return paths


def create_plan_key(pki_dir: Path, name: str = PLAN_KEY_NAME) -> Paths:
    paths = plan_key_paths(pki_dir, name)
    key = Ed25519PrivateKey.generate()
    _write_private(paths.key, _key_pem(key))
    public = key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    write_file(paths.cert, public, PUBLIC_MODE)
    return paths


def _retire(pki_dir: Path, public: Path, private: Path) -> Path:
    """Move `public` to retired/<UTC time>/ and delete `private`: what was signed by it can be told apart
    later, but nothing can be signed with it again."""
    folder = pki_dir / RETIRED_DIR / _now().strftime("%Y%m%dT%H%M%S.%fZ")
    folder.mkdir(parents=True, exist_ok=True)
    moved = folder / public.name
    public.rename(moved)
    private.unlink()
    return moved


def rotate_ca(pki_dir: Path, extra_names: dict[str, tuple[str, ...]] | None = None) -> list[str]:
    """A new CA, and every identity of `pki_dir` reissued under it: once the routers run with the new
    `ca.pem`, no leaf of the old CA connects (an old, stolen or renewed-away certificate is refused;
    Zenoh's TLS has no revocation lists, so this is the revocation). The old CA's certificate is
    retired, its key deleted. Returns the identities reissued."""
    CertificateAuthority.load(pki_dir)  # there is one to rotate (ConfigError if not)
    identities = sorted(
        p.stem for p in pki_dir.glob("*.pem") if p.stem != CA_NAME and p.with_suffix(".key").exists()
    )
    old = ca_paths(pki_dir)
    _retire(pki_dir, old.cert, old.key)
    ca = CertificateAuthority.create(pki_dir)
    for identity in identities:
        ca.issue(pki_dir, identity, (extra_names or {}).get(identity, ()))
    return identities


def revoke(pki_dir: Path, identity: str) -> str:
    """Revoke `identity`'s leaf alone: its generation counted up in `generations.json` and a new leaf
    (new key, new common name, the old one's extra names) issued; no other leaf changes. Once the
    routers run with access control rendered from this directory, the old certificate still completes
    TLS (Zenoh has no revocation lists) but its common name is granted nothing. Returns the new CN."""
    check_identity(identity)
    ca = CertificateAuthority.load(pki_dir)
    cert_path = identity_paths(pki_dir, identity).cert
    try:
        old = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except (OSError, ValueError) as err:
        raise ConfigError(f"{cert_path}: no certificate of {identity} to revoke ({err})") from None
    extra_names = _extra_names(old, identity)
    counts = generations(pki_dir)
    counts[identity] = counts.get(identity, 0) + 1
    write_file(pki_dir / GENERATIONS_FILE, json.dumps(counts, indent=1, sort_keys=True).encode(), PUBLIC_MODE)
    ca.issue(pki_dir, identity, extra_names)
    return certificate_name(identity, counts[identity])


def _extra_names(cert: x509.Certificate, identity: str) -> tuple[str, ...]:
    """The names `issue` was given for `cert` beyond the ones it adds itself."""
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    dns = [n for n in san.get_values_for_type(x509.DNSName) if n not in (identity, "localhost")]
    ips = [str(a) for a in san.get_values_for_type(x509.IPAddress) if str(a) != router_loopback(identity)]
    return (*dns, *ips)


def rotate_plan_key(pki_dir: Path, name: str = PLAN_KEY_NAME) -> str:
    """One step of a rotation of plan key `name` (a shard's: `shard_plan_key_name`); returns which:
    `staged` (a next key made: vehicles trust it beside the current one, `trusted_plan_keys`) or
    `promoted` (the next key becomes the current one: the coordinator restarted now signs with it, and
    vehicles stop trusting the retired key within `KEY_RECHECK_S`)."""
    current, staged = plan_key_paths(pki_dir, name), plan_key_paths(pki_dir, next_key_name(name))
    if not current.key.exists():
        raise ConfigError(f"{pki_dir}: no plan key to rotate (`rmmdet pki init` first)")
    if not staged.key.exists():
        create_plan_key(pki_dir, next_key_name(name))
        return "staged"
    _retire(pki_dir, current.cert, current.key)
    staged.key.rename(current.key)
    staged.cert.rename(current.cert)
    return "promoted"


@dataclass
class InitReport:
    created: list[str]
    kept: list[str]


def init_pki(
    pki_dir: Path,
    identities: list[str],
    extra_names: dict[str, tuple[str, ...]] | None = None,
    renew: bool = False,
) -> InitReport:
    """Make the CA, the plan-signing key, a certificate per identity and a plan key per shard identity,
    keeping what exists (all of the leaves are reissued with `renew`; the CA and plan keys never are)."""
    extra_names = extra_names or {}
    for identity in identities:
        check_identity(identity)
    report = InitReport([], [])
    pki_dir.mkdir(parents=True, exist_ok=True)
    if ca_paths(pki_dir).cert.exists():
        ca = CertificateAuthority.load(pki_dir)
        report.kept.append(CA_NAME)
    else:
        ca = CertificateAuthority.create(pki_dir)
        report.created.append(CA_NAME)
    if plan_key_paths(pki_dir).key.exists():
        report.kept.append(PLAN_KEY_NAME)
    else:
        create_plan_key(pki_dir)
        report.created.append(PLAN_KEY_NAME)
    for identity in identities:
        if (region := shard_region(identity)) is not None:
            name = shard_plan_key_name(region)
            if plan_key_paths(pki_dir, name).key.exists():
                report.kept.append(name)
            else:
                create_plan_key(pki_dir, name)
                report.created.append(name)
        paths = identity_paths(pki_dir, identity)
        if paths.cert.exists() and paths.key.exists() and not renew:
            report.kept.append(identity)
        else:
            ca.issue(pki_dir, identity, extra_names.get(identity, ()))
            report.created.append(identity)
    return report


def days_left(cert: x509.Certificate, now: dt.datetime | None = None) -> float:
    """Days until `cert` expires (negative: expired)."""
    return (cert.not_valid_after_utc - (now or _now())).total_seconds() / 86400.0


def common_name(cert_path: Path) -> str:
    """The CN of a PEM certificate (what Zenoh access control matches `cert_common_names` against)."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    values = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(values[0].value) if values else ""
