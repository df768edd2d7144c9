"""``stereopath features --homography`` with a malformed OpenCV XML/YAML file: one line, exit 2."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopath.host.cli import main


@pytest.fixture
def images(tmp_path):
    img = (np.random.default_rng(0).random((32, 32)) * 255).astype(np.uint8)
    paths = [tmp_path / "A.png", tmp_path / "B.png"]
    for p in paths:
        cv2.imwrite(str(p), img)
    return [str(p) for p in paths]


@pytest.mark.parametrize("text", [
    "<opencv_storage><H>1 2</H></opencv_storage>",                                           # parse error
    '<?xml version="1.0"?><opencv_storage><H>1 2 3 4 5 6 7 8 9</H></opencv_storage>',       # not a matrix node
])
def test_malformed_homography_file_is_one_line(tmp_path, images, capsys, text):
    bad = tmp_path / "bad.xml"
    bad.write_text(text)
    assert main(["features", *images, "--homography", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: not a readable OpenCV XML/YAML matrix file" in err and len(err.splitlines()) == 1


def test_load_homography_turns_a_parse_error_into_a_dataset_error(tmp_path):
    """Every caller of load_homography gets the DatasetError, not only the command."""
    from stereopath.device.errors import DatasetError
    from stereopath.host.evaluation.features import load_homography

    bad = tmp_path / "bad.xml"
    bad.write_text("<opencv_storage><H>1 2</H></opencv_storage>")
    with pytest.raises(DatasetError, match="not a readable OpenCV XML/YAML matrix file"):
        load_homography(bad)
