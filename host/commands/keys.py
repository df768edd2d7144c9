"""Generate CURVE key pairs for the device and its hosts (ZeroMQ certificates).

Writes DIR/NAME.key (public) and DIR/NAME.key_secret (secret, mode 0600).  The device needs
its own .key_secret and, in its clients directory, the .key of every host allowed to connect;
a host needs its own .key_secret and the device's .key saved as device.key in its key directory.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write the key files into (created if missing)")
    parser.add_argument("--name", required=True, help="key pair name, e.g. 'device' or the host's name")
    parser.add_argument("--force", action="store_true", help="overwrite existing key files of that name")


def run(args: argparse.Namespace) -> int:
    from stereopath.device.wire.security import generate_keypair

    public, secret = generate_keypair(args.dir, args.name, overwrite=args.force)
    print(f"public key: {public}")
    print(f"secret key: {secret}  (keep it on this machine only)")
    return 0
