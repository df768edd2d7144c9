"""``stereopath keys generate`` refuses a key directory or key file path that is not what it should be."""

from __future__ import annotations

import pytest

from stereopath.device.errors import ConfigError
from stereopath.device.wire.security import generate_keypair
from stereopath.host.cli import main

pytest.importorskip("zmq.auth")


def test_a_file_where_the_key_directory_should_be(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert main(["keys", "generate", str(afile), "--name", "host"]) == 2
    assert f"key directory {afile}: exists and is not a folder" in capsys.readouterr().err
    assert main(["keys", "generate", str(afile / "sub"), "--name", "host"]) == 2
    assert f"{afile} is not a folder" in capsys.readouterr().err
    assert afile.read_text() == "keep me"


def test_a_folder_where_a_key_file_should_be(tmp_path):
    (tmp_path / "host.key_secret").mkdir()
    with pytest.raises(ConfigError, match=r"host\.key_secret exists and is not a key file"):
        generate_keypair(tmp_path, "host", overwrite=True)
    assert (tmp_path / "host.key_secret").is_dir() and not (tmp_path / "host.key").exists()
