"""npp-sign: make an Ed25519 key pair, sign a run folder's seal, check a signature.

A signature says who certified a run and that nothing in it changed since (npp_ros.deployment.signing);
npp-deploy given the public key (its trusted_keys parameter) deploys only runs that key signed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from npp_ros.deployment.signing import (
    SIGNATURE_FILE,
    SigningError,
    generate_keys,
    load_public_keys,
    run_folder,
    sealed_digest,
    sign_run,
    signature_reasons,
)
from npp_ros.run.records import RunFileError
from npp_ros.run.store import RUN_FILE


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="npp-sign",
        description="Sign certified runs with Ed25519: npp-deploy with trusted_keys deploys only runs signed by "
        "one of them, unchanged since.",
    )
    commands = top.add_subparsers(dest="command", required=True)
    keygen = commands.add_parser("keygen", help="make a key pair: NAME.key (private, mode 0600) and NAME.pub")
    keygen.add_argument("name", type=Path, help="the files' path without suffix, e.g. keys/alice")
    run = commands.add_parser("run", help=f"sign a run folder's seal digest (writes FOLDER/{SIGNATURE_FILE})")
    run.add_argument("folder", type=Path, help="the run folder (holds run.sqlite)")
    run.add_argument("--key", type=Path, required=True, help="the private key (NAME.key from keygen)")
    verify = commands.add_parser("verify", help="check a run folder's signature against public keys")
    verify.add_argument("folder", type=Path, help="the run folder (holds run.sqlite and run.sig)")
    verify.add_argument("--trusted", type=Path, nargs="+", required=True, help="public keys (NAME.pub) trusted")
    return top


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == "keygen":
            private, public = args.name.with_suffix(".key"), args.name.with_suffix(".pub")
            private.parent.mkdir(parents=True, exist_ok=True)
            print(f"{private} and {public}: key {generate_keys(private, public)}")
        elif args.command == "run":
            signature = sign_run(args.folder, args.key)
            print(f"{run_folder(args.folder) / SIGNATURE_FILE}: seal {signature.digest[:16]}... signed by "
                  f"{signature.signer}")  # fmt: skip
        else:
            folder = run_folder(args.folder)
            digest = sealed_digest(folder / RUN_FILE)
            reasons, said = signature_reasons(folder, digest, load_public_keys(args.trusted))
            if reasons:
                print(f"npp-sign: {'; '.join(reasons)}", file=sys.stderr)
                return 1
            print(f"{folder}: {said}; seal {digest[:16]}...")
    except (SigningError, RunFileError) as exc:
        print(f"npp-sign: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
