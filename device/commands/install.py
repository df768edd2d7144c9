"""Install the capture service: system user, virtual environment, keys, configuration, systemd unit.

Creates the user 'stereopath' (groups video and i2c), a virtual environment with access to
the system picamera2 (/opt/stereopath/venv, --system-site-packages) with this package in it,
/etc/stereopath/device.toml (kept if present), the device's CURVE key pair (never
overwritten; the secret stays root-only and reaches the service through LoadCredential=),
/var/lib/stereopath/sessions, the i2c-dev module load, and the unit
stereopath-capture.service, enabled at boot, with a drop-in allowing exactly the devices of the
configured source.backend (libcamera's for picamera2, USB for depthai; rerun after changing it).
Idempotent: run it again after an update.
With --root DIR everything is written under DIR instead of / (accounts into DIR/etc/passwd and
DIR/etc/group, no pip, no systemctl): for preparing or inspecting a tree without touching
this system.  Append firmware_cfg/config.txt to /boot/firmware/config.txt yourself.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", default="/", metavar="DIR", help="install under DIR instead of / (default: /)")
    parser.add_argument("--dry-run", action="store_true", help="print what would change, change nothing")
    parser.add_argument("--host-key", action="append", default=[], metavar="HOST.key",
                        help="authorise a host: copy its public key into /etc/stereopath/clients (repeatable)")
    parser.add_argument("--backend", choices=("picamera2", "depthai", "replay", "sim"), default=None,
                        help="camera backend the unit's device drop-in is written for "
                             "(default: source.backend of /etc/stereopath/device.toml)")
    parser.add_argument("--python", default="/usr/bin/python3",
                        help="system Python the venv is made from (the one apt's python3-picamera2 is for)")


def run(args: argparse.Namespace) -> int:
    from stereopath.device.service.installer import UNIT_NAME, InstallChoices, install

    report = install(args.root, choices=InstallChoices(dry_run=args.dry_run, python=args.python,
                                                       host_keys=tuple(args.host_key), backend=args.backend))
    for action in report.actions:
        print(("would " if args.dry_run and not action.startswith("keep ") else "") + action)
    changed = len(report.changed)
    print(f"{'dry run: ' if args.dry_run else ''}{changed} change(s) under {report.root}"
          + ("" if changed else " (already installed)"))
    if report.device_public_key is not None:
        print(f"device public key (copy it to each host as KEYS/device.key): {report.device_public_key}"
              + (" (once installed)" if args.dry_run and not report.device_public_key.exists() else ""))
    more = "another host" if args.host_key else "a host"
    print(f"authorise {more}: copy its public HOST.key into /etc/stereopath/clients/ and "
          f"`systemctl reload {UNIT_NAME}`" if str(report.root) == "/" else
          f"host keys go into {report.root}/etc/stereopath/clients/")
    print("firmware: append firmware_cfg/config.txt to /boot/firmware/config.txt and reboot")
    return 0
