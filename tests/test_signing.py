"""Signed runs: npp-sign makes keys and signs a run's seal; the gate given trusted keys deploys only a run signed by
one of them, unchanged since, and names the signer it found otherwise."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
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
    with pytest.raises(GateRefusal, match=r"does not match the run as it stands .* changed after it was signed"):
        load_deployment(resealed, trusting(keys["alice"]))


def test_a_key_is_never_overwritten_and_every_command_has_help(keys: dict[str, Path]) -> None:
    assert npp_sign(["keygen", str(keys["alice"])]) == 2
    for args in ([], ["keygen"], ["run"], ["verify"]):
        shown = subprocess.run(
            [sys.executable, "-m", "npp_ros.cli.sign", *args, "--help"], capture_output=True, text=True, timeout=120
        )
        assert shown.returncode == 0 and "usage: npp-sign" in shown.stdout, (args, shown.stderr)
