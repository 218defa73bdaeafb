"""Signed runs: an Ed25519 signature over a run file's seal digest, kept beside it as ``run.sig``.

The seal (npp_ros.run.seal) proves that the file holds what its writer committed, but anyone with npp_ros's
code can edit a run and seal it again. A signature proves who certified: only the holder of the private key
can sign a digest, and the digest covers every stored value, so a signature that verifies says the run is the
one its signer signed, unchanged since. npp-deploy given trusted public keys refuses a run that is unsigned,
signed by another key, or changed after it was signed.

Keys are PEM files (PKCS#8 private, SubjectPublicKeyInfo public); a key is named by its fingerprint,
``ed25519:`` and the first 32 hex digits of the SHA-256 of its 32 raw bytes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from npp_ros.run.records import RunFileError
from npp_ros.run.store import RUN_FILE, RunStore

SIGNATURE_FILE = "run.sig"
SIGNATURE_FORMAT = "npp_ros.run-signature"
# Signed with the digest, so a signature means nothing in another context. Scheme 1 signed the digest alone;
# scheme 2 (every signature made now) signs the time of signing too, so no field run.sig reports goes unsigned.
_CONTEXTS = {1: b"npp_ros run seal v1\n", 2: b"npp_ros run seal v2\n"}
SCHEME = 2


class SigningError(ValueError):
    """A key or a signature that cannot be used, with the reason."""


def fingerprint(key: Ed25519PublicKey) -> str:
    raw = key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return "ed25519:" + hashlib.sha256(raw).hexdigest()[:32]


def generate_keys(private_path: Path, public_path: Path) -> str:
    """A new key pair in two PEM files (the private one readable by its owner only); its fingerprint."""
    for path in (private_path, public_path):
        if path.exists():
            raise SigningError(f"{path} exists; choose another name (a key is never overwritten)")
    key = Ed25519PrivateKey.generate()
    private = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(private)
    public = key.public_key()
    public_path.write_bytes(
        public.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    )
    return fingerprint(public)


def load_private_key(path: Path) -> Ed25519PrivateKey:
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise SigningError(f"cannot read the private key {path}: {exc}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SigningError(f"{path} is not an Ed25519 private key")
    return key


def load_public_key(path: Path) -> Ed25519PublicKey:
    try:
        key = serialization.load_pem_public_key(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise SigningError(f"cannot read the public key {path}: {exc}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise SigningError(f"{path} is not an Ed25519 public key")
    return key


def load_public_keys(paths: Sequence[str | Path]) -> tuple[Ed25519PublicKey, ...]:
    return tuple(load_public_key(Path(p)) for p in paths)


@dataclass(frozen=True)
class RunSignature:
    """What run.sig holds: the seal digest signed, by which key, when, and the signature."""

    digest: str
    public_key: str  # the signer's raw public key, hex
    signer: str  # its fingerprint
    signed_at: str
    signature: str  # hex
    format: str = SIGNATURE_FORMAT
    scheme: int = 1  # what was signed: 1 the digest; 2 the digest and signed_at (absent from older files: 1)

    def key(self) -> Ed25519PublicKey:
        return Ed25519PublicKey.from_public_bytes(bytes.fromhex(self.public_key))

    def message(self, digest: str) -> bytes:
        """The bytes a signature of this scheme covers for a run of seal ``digest``."""
        signed = digest if self.scheme == 1 else f"{digest}\n{self.signed_at}"
        return _CONTEXTS[self.scheme] + signed.encode()

    def verifies_by(self, key: Ed25519PublicKey, digest: str) -> bool:
        """Whether the signature is ``key``'s over a run of seal ``digest`` (and, scheme 2, over signed_at)."""
        try:
            key.verify(bytes.fromhex(self.signature), self.message(digest))
        except (InvalidSignature, ValueError):
            return False
        return True

    def verifies(self, digest: str) -> bool:
        """Whether the signature is by the key run.sig itself carries: says nothing of who signed (anyone can write
        any key there); only a trusted key's verification does (:func:`signature_reasons`)."""
        return self.verifies_by(self.key(), digest)


def run_folder(run: str | Path) -> Path:
    """The run folder of a folder or of its run.sqlite."""
    path = Path(run)
    return path.parent if path.is_file() else path


def sealed_digest(run_file: Path) -> str:
    """The run file's seal digest, once checked intact; a SigningError for a file that is unsealed or altered."""
    with RunStore.open(run_file) as store:
        seal = store.check_seal()
    if seal.mismatches:
        raise SigningError(f"{run_file} no longer matches its seal ({', '.join(seal.mismatches)}): not signed")
    if not seal.sealed:
        raise SigningError(
            f"{run_file} is unsealed (written before run files were sealed): resume the run once, or open it "
            "for writing, to seal it, then sign"
        )
    return seal.digest


def sign_run(run: str | Path, private_key: Path) -> RunSignature:
    """Sign a run folder's seal digest; writes run.sig beside run.sqlite (replacing an earlier signature)."""
    folder = run_folder(run)
    key = load_private_key(private_key)
    digest = sealed_digest(folder / RUN_FILE)
    public = key.public_key()
    unsigned = RunSignature(
        digest=digest,
        public_key=public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw).hex(),
        signer=fingerprint(public),
        signed_at=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        signature="",
        scheme=SCHEME,
    )
    signature = dataclasses.replace(unsigned, signature=key.sign(unsigned.message(digest)).hex())
    tmp = folder / f".{SIGNATURE_FILE}.{os.getpid()}.new"
    tmp.write_text(json.dumps(asdict(signature), indent=2) + "\n")
    os.replace(tmp, folder / SIGNATURE_FILE)
    return signature


def read_signature(folder: Path) -> RunSignature | None:
    """run.sig of a run folder, or None when it has none; a RunFileError for one that cannot be read."""
    path = folder / SIGNATURE_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        signature = RunSignature(**record)
        if signature.format != SIGNATURE_FORMAT:
            raise ValueError(f"format {signature.format!r}")
        if signature.scheme not in _CONTEXTS or isinstance(signature.scheme, bool):
            raise ValueError(f"scheme {signature.scheme!r}")
        signature.key()  # a key of the right length
        bytes.fromhex(signature.signature)
    except (OSError, ValueError, TypeError) as exc:
        raise RunFileError(f"{path} is not a readable run signature: {exc}") from None
    return signature


def signature_reasons(folder: Path, digest: str, trusted: Sequence[Ed25519PublicKey]) -> tuple[list[str], str]:
    """Why the run may not be deployed for its signature (none when a trusted key verifies it, or when no key is
    trusted), and one line that says who signed, for the log.

    The identity is the trusted key that verifies the signature over the file's own seal digest: nothing in run.sig
    chooses the key it is checked with. Its ``public_key``, ``signer`` and ``digest`` fields are the signer's claims,
    used only to say why a signature fails; a run.sig that names a trusted fingerprint beside another key's
    signature verifies under no trusted key and is refused as what it is.
    """
    try:
        signature = read_signature(folder)
    except RunFileError as exc:
        return [str(exc)], "signature unreadable"
    trusted_names = ", ".join(fingerprint(k) for k in trusted)
    if signature is None:
        refused = [f"the run is unsigned; this deployment trusts only runs signed by {trusted_names}"]
        return (refused if trusted else []), "unsigned (no run.sig)"
    if not trusted:
        said = f"run.sig names {signature.signer} at {signature.signed_at}"
        return [], said + " (not checked: no trusted keys given)"
    verifying = next((key for key in trusted if digest and signature.verifies_by(key, digest)), None)
    if verifying is not None:
        said_at = signature.signed_at
        when = f"at {said_at}" if signature.scheme >= 2 else f"(its time unsigned: run.sig says {said_at})"
        return [], f"signed by {fingerprint(verifying)} {when}"
    return [_why_unverified(signature, digest, trusted_names)], f"not verified by a trusted key ({trusted_names})"


def _why_unverified(signature: RunSignature, digest: str, trusted_names: str) -> str:
    """The true reason no trusted key verifies run.sig, in one line."""
    claimed_key = fingerprint(signature.key())
    own = signature.verifies(signature.digest)  # a genuine signature by the key run.sig carries, over some digest
    if not digest:
        return "the run file is unsealed, so there is no digest a signature could be over"
    if not own:
        return (
            f"run.sig holds no valid signature by the key it carries ({claimed_key}) over what it names (seal "
            f"{signature.digest[:16]}..., signed at {signature.signed_at}): the signature file was altered or forged"
        )
    if claimed_key != signature.signer:
        return (
            f"run.sig claims signer {signature.signer} but its signature is by {claimed_key}, which this deployment "
            f"does not trust ({trusted_names}): a forged signer"
        )
    if signature.digest != digest:
        return (
            f"the run changed after {claimed_key} signed it (signed seal {signature.digest[:16]}..., the file's "
            f"{digest[:16]}...)"
        )
    return f"the run is signed by {claimed_key}, which this deployment does not trust ({trusted_names})"
