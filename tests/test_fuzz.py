"""Bad input: malformed or out-of-range scenes, NaN/inf, truncated or corrupt projection
stores, missing run directories. Each gives a one-line error naming the file or key and
what is allowed (a :class:`~clrecon.core.errors.ClreconError`), the CLI exits non-zero without a
traceback unless ``--debug``; fuzzed scene files and stores raise nothing else."""

from __future__ import annotations

import random
import warnings

import numpy as np
import pytest

from clrecon.cli import main
from clrecon.config.scene import SCENE_DIR, load_scene, scene_from_dict
from clrecon.core.errors import ClreconError, SceneError, StoreError
from clrecon.simulation.store import ProjectionStore

# Sizes of the fuzz loops (seeded: the same cases every run).
N_SCENE_FUZZ = 400
N_STORE_FUZZ = 120


def _one_line_cli_error(capsys, argv, *fragments):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in err, (f, err)
    return err


# ---------------------------------------------------------------------------------------
# scenes
@pytest.mark.parametrize("text,fragments", [
    ("[scanner\nn_cols = 3", ["malformed TOML"]),
    ("[scanner]\nn_colz = 96", ["scanner.n_colz: unknown key", "did you mean 'n_cols'"]),
    ("colour = 1", ["colour: unknown key", "valid keys"]),
    ("[recon]\nresp_bins = 99", ["recon.resp_bins = 99", "an integer in 1..50"]),
    ("[noise]\ni0_photons = nan", ["noise.i0_photons = nan", "a number in (0, 1e15]"]),
    ("[noise]\ni0_photons = 1e19", ["noise.i0_photons = 1e+19", "a number in (0, 1e15]"]),
    ("[scan]\npitches = 0.5", ["scan.pitches = 0.5", "a non-empty list"]),            # scalar for a list
    ("[scan]\npitches = [0.1, inf]", ["scan.pitches", "(0, 2]"]),
    ("[signals]\nrhythm = 3", ["signals.rhythm = 3", "one of periodic"]),
    ("scanner = 5", ["scanner: expected a table"]),
    ("[scanner]\nsid_mm = 1e-308", ["derived geometry", "not finite"]),               # overflow
    ("[scanner]\nsdd_mm = 1e308", ["derived geometry", "not finite"]),
    ("[scan]\npitches = [1.5]", ["pitch 1.5 leaves (slice, view) pairs without data",
                                 "the largest pitch that covers every (slice, view) is 0.8870"]),
])
def test_bad_scene_files_give_one_line_errors_naming_file_and_key(tmp_path, text, fragments):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(SceneError) as e:
        load_scene(f)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(f))
    for frag in fragments:
        assert frag in msg, (frag, msg)


def test_missing_and_binary_scene_files(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.toml")
    f = tmp_path / "binary.toml"
    f.write_bytes(bytes(range(256)))
    with pytest.raises(SceneError, match="malformed TOML"):
        load_scene(f)


def test_cli_bad_scene_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys):
    f = tmp_path / "bad.toml"
    f.write_text("[recon]\nnx = -3\n")
    _one_line_cli_error(capsys, ["run", "--scene", str(f), "--out", str(tmp_path / "out")],
                        str(f), "recon.nx = -3", "an integer > 0")
    with pytest.raises(SceneError):
        main(["--debug", "run", "--scene", str(f), "--out", str(tmp_path / "out")])


def _mutate_scene(rnd: random.Random, texts) -> bytes:
    b = bytearray(rnd.choice(texts))
    op = rnd.randrange(5)
    if op == 0:                                   # truncated
        return bytes(b[:rnd.randrange(len(b))])
    if op == 1:                                   # random bytes flipped
        for _ in range(rnd.randint(1, 5)):
            b[rnd.randrange(len(b))] = rnd.randrange(256)
        return bytes(b)
    if op == 2:                                   # lines shuffled (keys move between tables)
        lines = bytes(b).split(b"\n")
        rnd.shuffle(lines)
        return b"\n".join(lines)
    if op == 3:                                   # random bytes
        return bytes(rnd.randrange(256) for _ in range(rnd.randrange(200)))
    lines = bytes(b).split(b"\n")                 # one value replaced by an odd one
    j = rnd.randrange(len(lines))
    if b"=" in lines[j]:
        k, _, _ = lines[j].partition(b"=")
        lines[j] = k + b"= " + rnd.choice([b"-1", b"0", b"1e400", b"nan", b"-inf", b'"x"', b"[]", b"{}",
                                           b"9999999999999999999999", b"1979-05-27", b"true",
                                           b'[1, "a"]', b"0.0", b"1e-320", b"1e308", b"[0.5, 0.5]"])
    return b"\n".join(lines)


def test_fuzzed_scene_files_raise_only_scene_errors(tmp_path):
    rnd = random.Random(20240611)
    texts = [p.read_bytes() for p in sorted(SCENE_DIR.glob("*.toml"))]
    n_ok = n_err = 0
    for i in range(N_SCENE_FUZZ):
        f = tmp_path / f"fuzz{i}.toml"
        f.write_bytes(_mutate_scene(rnd, texts))
        try:
            load_scene(f)
            n_ok += 1
        except SceneError as e:                   # anything else fails the test
            assert "\n" not in str(e)
            n_err += 1
    assert n_ok > 0 and n_err > 0                 # the fuzz reaches both outcomes


def test_fuzzed_scene_dicts_raise_only_scene_errors():
    """Random values of every type in random keys of every section."""
    from dataclasses import fields

    from clrecon.config.scene import SECTIONS
    rnd = random.Random(7)
    values = [0, 1, -1, 2 ** 63 - 1, -2 ** 63, 10 ** 30, 0.0, 1e308, -1e308, 1e-308, 5e-324, float("inf"),
              float("nan"), True, "x", [], [1], [1.0, 2.0], {}, {"a": 1}, 0.5, 3]
    for _ in range(2000):
        d = {}
        for sec, cls in SECTIONS.items():
            if rnd.random() < 0.5:
                names = [f.name for f in fields(cls)]
                d[sec] = {k: rnd.choice(values) for k in rnd.sample(names, rnd.randint(1, 3))}
        try:
            scene_from_dict(d)
        except SceneError:
            pass


# ---------------------------------------------------------------------------------------
# projection stores
@pytest.fixture
def small_store(tmp_path):
    """A finished store of a 40-projection scan filled with known values (no projector)."""
    scene = load_scene("tiny").replace(scan={"n_projections": 40})
    st = ProjectionStore.open(scene, 0.1, cache_dir=tmp_path)
    data = np.random.default_rng(0).random((len(st),) + st.shape[1:]).astype(np.float32)
    with st.writing():
        st.write(np.arange(len(st)), data)
    st.close()
    return scene, st.path, data


def _reopen(scene, cache):
    return ProjectionStore.open(scene, 0.1, cache_dir=cache, create=False)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_in_a_store_is_an_error_naming_file_and_projection(tmp_path, bad):
    scene = load_scene("tiny").replace(scan={"n_projections": 40})
    st = ProjectionStore.open(scene, 0.1, cache_dir=tmp_path)
    data = np.ones((40,) + st.shape[1:], np.float32)
    data[17, 3, 5] = bad
    with st.writing():
        st.write(np.arange(40), data)
    assert st.read(0, 17).shape == (17,) + st.shape[1:]          # the good part still reads
    for noisy in (False, True):
        with pytest.raises(StoreError) as e:
            st.read(10, 30, noisy=noisy)
        assert str(st.path) in str(e.value) and "projections 17..17" in str(e.value)
        assert "NaN or inf" in str(e.value) and "\n" not in str(e.value)
    st.close()


def test_truncated_store_is_an_error(small_store):
    scene, path, _ = small_store
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    with pytest.raises(StoreError, match="corrupt or truncated") as e:
        _reopen(scene, path.parent)
    assert str(path) in str(e.value)


def test_corrupt_chunk_is_caught_by_its_checksum(small_store):
    """Bytes changed inside the compressed data: the Fletcher-32 checksum fails on read."""
    scene, path, data = small_store
    import h5py
    with h5py.File(path, "r") as f:
        offset = f["projections"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    for j in range(offset + 100, offset + 108):
        raw[j] ^= 0x5A
    path.write_bytes(bytes(raw))
    st = _reopen(scene, path.parent)
    with pytest.raises(StoreError, match="corrupt or truncated"):
        st.read(0, len(st))
    st.close()


def test_missing_store_is_an_error(tmp_path):
    with pytest.raises(StoreError, match="no projection store"):
        _reopen(load_scene("tiny"), tmp_path)


def test_fuzzed_stores_raise_only_store_errors_and_never_return_wrong_numbers(small_store):
    scene, path, data = small_store
    good = path.read_bytes()
    rnd = random.Random(3)
    outcomes = {"error": 0, "read": 0}
    for _ in range(N_STORE_FUZZ):
        b = bytearray(good)
        op = rnd.randrange(3)
        if op == 0:
            b = b[:rnd.randrange(len(b))]
        elif op == 1:
            for _ in range(rnd.randint(1, 20)):
                b[rnd.randrange(len(b))] = rnd.randrange(256)
        else:
            j = rnd.randrange(len(b))
            b[j:j + rnd.randrange(1, 4000)] = bytes(rnd.randrange(256) for _ in range(100))
        path.write_bytes(bytes(b))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                st = _reopen(scene, path.parent)
            try:
                got = st.read(0, len(st))
            finally:
                st.close()
        except StoreError as e:                   # anything else fails the test
            assert "\n" not in str(e)
            outcomes["error"] += 1
            continue
        np.testing.assert_array_equal(got, data)  # bytes the data does not depend on
        outcomes["read"] += 1
    assert outcomes["error"] > N_STORE_FUZZ // 2


# ---------------------------------------------------------------------------------------
# run directories
def test_missing_run_directory_is_a_one_line_error(tmp_path, capsys):
    missing = tmp_path / "no-such-run"
    _one_line_cli_error(capsys, ["export", str(missing), "--format", "nifti"], str(missing), "no such run directory")
    with pytest.raises(ClreconError):
        main(["--debug", "export", str(missing), "--format", "nifti"])


def test_run_directory_with_a_corrupt_volume_file(tmp_path, capsys):
    (tmp_path / "volumes.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    _one_line_cli_error(capsys, ["export", str(tmp_path), "--format", "nifti"], "volumes.h5",
                        "not a readable HDF5 file")
