"""Dataset integrity (jtraj.dataset.store): bytes flipped in a chunk file's data array,
in a summary field, in its header attributes and in its HDF5 superblock are detected by
``verify``, ``info`` and ``load``, which name the file, and a resumed build solves the
corrupt chunk again, to the same values. The fast stand-in solver of
tests/test_dataset.py writes the chunks (no compilation)."""

import os

import h5py
import numpy as np
import pytest

from jtraj import dataset
from jtraj.cli import main as cli_main
from jtraj.dataset import store

FAKE = "jtraj.dataset.testing:fake_solve_batch"


def _spec():
    return dataset.make_spec("serial3", 16, 3, N=6, batch=8, solver=FAKE)


@pytest.fixture
def built(tmp_path):
    """A 16-pair dataset of two chunks and a copy of its arrays."""
    path = str(tmp_path / "d")
    dataset.build(_spec(), path, progress=False)
    data = dataset.load(path)
    return path, {k: np.array(data[k]) for k in data if k != "metadata"}


def _chunk(path, c=1):
    return os.path.join(path, "chunks", store.chunk_name(c))


def _flip(file, offset):
    with open(file, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x10]))


def _data_offset(file, field):
    """Where the stored bytes of ``field`` are, and how many (its one HDF5 chunk)."""
    with h5py.File(file, "r") as f:
        info = f[field].id.get_chunk_info(0)
        return info.byte_offset, info.size


def _find(file, needle: bytes):
    with open(file, "rb") as fh:
        data = fh.read()
    at = data.find(needle)
    assert at >= 0 and data.find(needle, at + 1) < 0, needle  # once
    return at


def _check_detected_and_resolved(path, arrays, capsys, field_read):
    bad = _chunk(path)
    # verify and info name the file and exit 1
    assert cli_main(["dataset", "verify", path]) == 1
    out = capsys.readouterr().out
    assert "1 CORRUPT" in out and f"{bad}: corrupt chunk" in out, out
    assert cli_main(["dataset", "info", path]) == 1
    out = capsys.readouterr().out
    assert "CORRUPT chunks: 1" in out and f"{bad}: corrupt chunk" in out and "chunks 1/2" in out, out
    # load names the file and says corrupt (when the header is damaged, at once; else when
    # the damaged field is read)
    with pytest.raises(ValueError, match=f"{bad}: corrupt chunk"):
        dataset.load(path)[field_read]
    # a resume solves it again instead of counting it done, to the same values
    logs = []
    s = dataset.build(_spec(), path, progress=False, log=logs.append)
    assert s["complete"] and s["new_pairs"] == 8, s
    assert any("chunk 1 is solved again" in ln and "corrupt" in ln for ln in logs), logs
    data = dataset.load(path)
    for k, v in arrays.items():
        np.testing.assert_array_equal(data[k], v, err_msg=k)
    assert dataset.verify(path)["intact"] == [0, 1]
    assert cli_main(["dataset", "verify", path]) == 0


def test_a_flipped_byte_in_a_data_array(built, capsys):
    path, arrays = built
    offset, size = _data_offset(_chunk(path), "q")
    _flip(_chunk(path), offset + size // 2)
    with pytest.raises(ValueError, match="field 'q' fails its Fletcher-32 checksum"):
        store.verify_chunk(_chunk(path))
    _check_detected_and_resolved(path, arrays, capsys, "q")


def test_a_flipped_byte_in_a_summary_field(built, capsys):
    path, arrays = built
    offset, size = _data_offset(_chunk(path), "cost")
    _flip(_chunk(path), offset + 3)
    _check_detected_and_resolved(path, arrays, capsys, "cost")


def test_a_field_rewritten_with_a_valid_fletcher32_is_caught_by_its_sha256(built, capsys):
    path, arrays = built
    with h5py.File(_chunk(path), "a") as f:
        f["T"][0] = 123.0  # HDF5 recomputes the Fletcher-32 checksum: only the SHA-256 sees it
    with pytest.raises(ValueError, match="field 'T' does not match its SHA-256"):
        store.verify_chunk(_chunk(path))
    _check_detected_and_resolved(path, arrays, capsys, "T")


def test_a_flipped_byte_in_the_header_attributes(built, capsys):
    path, arrays = built
    # inside the identity JSON that each chunk repeats: '"seed":3' -> '"seed":#'
    _flip(_chunk(path), _find(_chunk(path), b'"seed": 3') + len(b'"seed": '))
    with pytest.raises(ValueError, match="header attributes or list of fields do not match"):
        store.verify_chunk(_chunk(path))
    _check_detected_and_resolved(path, arrays, capsys, "q")


def test_a_flipped_byte_in_the_hdf5_superblock(built, capsys):
    path, arrays = built
    _flip(_chunk(path), 1)  # the format signature: HDF5 cannot open the file
    with pytest.raises(ValueError, match="HDF5 cannot read it"):
        store.verify_chunk(_chunk(path))
    _check_detected_and_resolved(path, arrays, capsys, "q")


def test_chunks_without_checksums_stay_readable_and_are_reported(built, capsys):
    path, arrays = built
    with h5py.File(_chunk(path, 0), "a") as f:  # as written before the SHA-256 checksums existed
        for k in ("digest", "integrity"):
            del f.attrs[k]
        for k in f.keys():
            del f[k].attrs["sha256"]
    r = dataset.verify(path)
    assert r["older"] == [0] and r["intact"] == [1] and not r["corrupt"]
    np.testing.assert_array_equal(dataset.load(path)["q"], arrays["q"])
    assert cli_main(["dataset", "verify", path]) == 0
    assert "1 intact by Fletcher-32 only" in capsys.readouterr().out
