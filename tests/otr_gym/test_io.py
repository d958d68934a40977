"""The one safe ``.npz`` reader (``otr_gym.io.load_npz``): every bad file is named with its problem,
and nothing is ever unpickled or suggested to be."""

from __future__ import annotations

import numpy as np
import pytest

from otr_gym.io import NpzError, load_npz, npz_keys, save_npz


@pytest.fixture
def good(tmp_path):
    return save_npz(tmp_path / "good.npz", {"a": np.arange(3.0), "name": np.array("walk")})


def test_an_archive_of_ours_loads_every_array(good):
    data = load_npz(good)
    assert sorted(data) == ["a", "name"]
    np.testing.assert_array_equal(data["a"], [0.0, 1.0, 2.0])
    assert str(data["name"]) == "walk"
    assert npz_keys(good) == ("a", "name")


def test_a_text_file_named_npz_is_not_an_archive_and_no_one_suggests_unpickling(tmp_path):
    path = tmp_path / "notes.npz"
    path.write_text("hello, this is not an array file\n")
    with pytest.raises(NpzError) as info:
        load_npz(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not a NumPy .npz archive (starts with the text 'hello")
    assert "pickle" not in message


def test_a_truncated_archive_says_so(tmp_path, good):
    path = tmp_path / "cut.npz"
    path.write_bytes(good.read_bytes()[:100])
    with pytest.raises(NpzError, match=rf"^{path}: not a NumPy .npz archive \(truncated or not a zip archive"):
        load_npz(path)
    with pytest.raises(NpzError, match="truncated or not a zip archive"):
        npz_keys(path)


def test_an_empty_file_says_so(tmp_path):
    path = tmp_path / "empty.npz"
    path.touch()
    with pytest.raises(NpzError, match=rf"^{path}: empty file \(0 bytes\)"):
        load_npz(path)


def test_a_single_npy_array_renamed_npz_is_named_as_such(tmp_path):
    path = tmp_path / "array.npz"
    with open(path, "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(NpzError, match=rf"^{path}: not a NumPy .npz archive \(a single-array .npy file\)"):
        load_npz(path)


def test_an_object_member_is_refused_without_unpickling_it(tmp_path):
    path = tmp_path / "objects.npz"
    np.savez(path, ok=np.zeros(2), bad=np.array([{"x": 1}], dtype=object))
    with pytest.raises(NpzError) as info:
        load_npz(path)
    message = str(info.value)
    assert message.startswith(f"{path}: member 'bad' holds Python objects (pickled data)")
    assert "allow_pickle" not in message


def test_a_missing_file_is_file_not_found_naming_it(tmp_path):
    with pytest.raises(FileNotFoundError, match=rf"{tmp_path / 'nope.npz'}: no such file"):
        load_npz(tmp_path / "nope.npz")


def _read_reference(path):
    from otr_gym.reference import Reference

    return Reference.load(path)


def _read_demonstration(path):
    from retarget.inputs.readers import load_demonstration

    return load_demonstration(path)


def _read_deploy_log(path):
    from agents.deploy.log import DeployLog

    return DeployLog.load(path)


@pytest.mark.parametrize("read", [_read_reference, _read_demonstration, _read_deploy_log],
                         ids=["reference", "demonstration", "deploy log"])
def test_every_npz_reader_names_a_text_file_as_not_an_archive(tmp_path, read):
    """``otr retarget``/``score``/``verify``/``inspect``/``deploy --replay`` read through these."""
    path = tmp_path / "notes.npz"
    path.write_text("hello\n")
    with pytest.raises(ValueError) as info:
        read(path)
    assert str(info.value) == f"{path}: not a NumPy .npz archive (starts with the text 'hello')"
