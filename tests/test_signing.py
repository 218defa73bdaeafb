"""Signed runs: npp-sign makes keys and signs a run's seal; the gate given trusted keys deploys only a run signed by
one of them, unchanged since, and names the signer it found otherwise."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from deploy_runs import FINGERPRINT, altered_copy, make_run

from npp_ros.cli.sign import main as npp_sign
from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.deployment.signing import SIGNATURE_FILE, fingerprint, load_public_key, read_signature


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two key pairs made by npp-sign keygen: alice's (trusted) and mallory's."""
    folder = tmp_path_factory.mktemp("keys")
    for name in ("alice", "mallory"):
        assert npp_sign(["keygen", str(folder / name)]) == 0
    assert (folder / "alice.key").stat().st_mode & 0o077 == 0  # the private key is its owner's only
    return {name: folder / name for name in ("alice", "mallory")}


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run(tmp_path_factory.mktemp("signed") / "good")


def signed_copy(good: Path, folder: Path, key: Path) -> Path:
    shutil.copytree(good, folder)
    assert npp_sign(["run", str(folder), "--key", str(key.with_suffix(".key"))]) == 0
    return folder


def trusting(*keys: Path) -> Acceptance:
    return Acceptance(
        model_fingerprint=FINGERPRINT, trusted_keys=tuple(load_public_key(k.with_suffix(".pub")) for k in keys)
    )


def test_a_run_signed_by_a_trusted_key_is_accepted(good: Path, keys: dict[str, Path], tmp_path: Path) -> None:
    run = signed_copy(good, tmp_path / "run", keys["alice"])
    alice = fingerprint(load_public_key(keys["alice"].with_suffix(".pub")))
    deployment = load_deployment(run, trusting(keys["mallory"], keys["alice"]))
    assert deployment.signed.startswith(f"signed by {alice}"), deployment.signed
    signature = read_signature(run)
    assert signature is not None and signature.digest == deployment.seal.digest
    assert npp_sign(["verify", str(run), "--trusted", str(keys["alice"].with_suffix(".pub"))]) == 0


def test_a_run_signed_by_an_untrusted_key_is_refused_naming_its_signer(
    good: Path, keys: dict[str, Path], tmp_path: Path
) -> None:
    run = signed_copy(good, tmp_path / "run", keys["mallory"])
    mallory = fingerprint(load_public_key(keys["mallory"].with_suffix(".pub")))
    with pytest.raises(GateRefusal, match=f"signed by {mallory}, which this deployment does not trust"):
        load_deployment(run, trusting(keys["alice"]))
    with pytest.raises(GateRefusal, match="does not trust"):  # no override for it
        load_deployment(run, Acceptance(override=True, trusted_keys=trusting(keys["alice"]).trusted_keys))
    assert npp_sign(["verify", str(run), "--trusted", str(keys["alice"].with_suffix(".pub"))]) == 1


def test_an_unsigned_run_is_refused_when_keys_are_trusted_and_said_unsigned_otherwise(
    good: Path, keys: dict[str, Path]
) -> None:
    with pytest.raises(GateRefusal, match="the run is unsigned; this deployment trusts only runs signed by ed25519:"):
        load_deployment(good, trusting(keys["alice"]))
    assert load_deployment(good, Acceptance(model_fingerprint=FINGERPRINT)).signed == "unsigned (no run.sig)"


def test_an_edited_signed_run_is_refused(good: Path, keys: dict[str, Path], tmp_path: Path) -> None:
    """Edited from outside, the seal names the edit; edited and sealed again (as anyone with this code can), the
    signature no longer verifies."""
    run = signed_copy(good, tmp_path / "run", keys["alice"])
    edit = ("UPDATE meta SET value = '3.0' WHERE key = 'epsilon'", ())
    with pytest.raises(GateRefusal, match="meta 'epsilon' changed after the run wrote it"):
        load_deployment(altered_copy(run, tmp_path / "edited", edit), trusting(keys["alice"]))
    resealed = altered_copy(run, tmp_path / "resealed", edit, resealed=True)
    assert (resealed / SIGNATURE_FILE).is_file()
    with pytest.raises(GateRefusal, match=r"the run changed after ed25519:\w+ signed it \(signed seal"):
        load_deployment(resealed, trusting(keys["alice"]))


def forged(run: Path, folder: Path, **fields: str) -> Path:
    """A copy of a signed run whose run.sig has ``fields`` written over, as anyone who may write the folder can."""
    shutil.copytree(run, folder)
    record = json.loads((folder / SIGNATURE_FILE).read_text())
    record.update(fields)
    (folder / SIGNATURE_FILE).write_text(json.dumps(record))
    return folder


def test_a_signature_is_checked_with_the_trusted_keys_only_and_no_field_of_run_sig_forges_one(
    good: Path, keys: dict[str, Path], tmp_path: Path
) -> None:
    """An editor widens what the run claims, seals it again, signs it with a key of their own and writes the trusted
    key's fingerprint (and its public key) into run.sig: no trusted key verifies the signature, so it is refused,
    for each field of run.sig written over and for the trusted signer's real signature moved onto the edited run."""
    alice_pub = load_public_key(keys["alice"].with_suffix(".pub"))
    alice = fingerprint(alice_pub)
    alice_raw = alice_pub.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw).hex()
    genuine = read_signature(signed_copy(good, tmp_path / "genuine", keys["alice"]))
    assert genuine is not None and genuine.scheme == 2
    edit = ("UPDATE meta SET value = '3.0' WHERE key = 'epsilon'", ())
    edited = signed_copy(altered_copy(good, tmp_path / "edited", edit, resealed=True), tmp_path / "e", keys["mallory"])
    mallory = read_signature(edited)
    assert mallory is not None
    cases = {
        "signer": (edited, {"signer": alice}, "claims signer"),
        "public_key": (edited, {"public_key": alice_raw}, "altered or forged"),
        "signer and public_key": (edited, {"signer": alice, "public_key": alice_raw}, "altered or forged"),
        "signature (the trusted one's, moved)": (
            edited, {"signer": alice, "public_key": alice_raw, "signature": genuine.signature}, "altered or forged"
        ),
        "everything but the digest (alice's run.sig whole)": (
            edited, {k: v for k, v in asdict(genuine).items() if k != "digest"}, "altered or forged"
        ),
        "digest (alice's run.sig whole)": (edited, asdict(genuine), r"changed after ed25519:\w+ signed it"),
        "signed_at": (tmp_path / "genuine", {"signed_at": "2020-01-01 00:00:00 UTC"}, "altered or forged"),
        "scheme": (tmp_path / "genuine", {"scheme": 1}, "altered or forged"),
    }  # fmt: skip
    for k, (source, fields, reason) in enumerate(cases.values()):
        run = forged(source, tmp_path / f"forged{k}", **fields)
        with pytest.raises(GateRefusal, match=reason):
            load_deployment(run, trusting(keys["alice"]))
        assert npp_sign(["verify", str(run), "--trusted", str(keys["alice"].with_suffix(".pub"))]) == 1
    bad_format = forged(tmp_path / "genuine", tmp_path / "format", format="other")
    with pytest.raises(GateRefusal, match="is not a readable run signature"):
        load_deployment(bad_format, trusting(keys["alice"]))
    # Untouched, alice's signature still verifies, by her key alone.
    assert load_deployment(tmp_path / "genuine", trusting(keys["alice"])).signed.startswith(f"signed by {alice} at")


def test_a_key_is_never_overwritten_and_every_command_has_help(keys: dict[str, Path]) -> None:
    assert npp_sign(["keygen", str(keys["alice"])]) == 2
    for args in ([], ["keygen"], ["run"], ["verify"]):
        shown = subprocess.run(
            [sys.executable, "-m", "npp_ros.cli.sign", *args, "--help"], capture_output=True, text=True, timeout=120
        )
        assert shown.returncode == 0 and "usage: npp-sign" in shown.stdout, (args, shown.stderr)
