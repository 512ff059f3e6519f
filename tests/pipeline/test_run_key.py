"""The run key's recon table (:func:`clrecon.pipeline.context.hashed_recon`): a registered method's
knobs are in it whole wherever the run makes that method, so a changed default cannot let an
interrupted run resume with volumes or a motion model made under the old one."""

from clrecon.config.scene import load_scene
from clrecon.pipeline.context import hashed_recon


def _recon():
    return load_scene("demo").to_dict()["recon"]


def test_a_run_without_the_registered_methods_does_not_hash_their_knobs():
    r = _recon()
    other = dict(r, mc=dict(r["mc"], rounds=r["mc"]["rounds"] + 1),
                 mcir=dict(r["mcir"], epochs=r["mcir"]["epochs"] + 1))
    methods = ("barycentric", "local_linear")
    assert hashed_recon(r, methods) == hashed_recon(other, methods)
    assert "mc" not in hashed_recon(r, methods) and "mcir" not in hashed_recon(r, methods)


def test_mc_hashes_its_knobs_at_their_defaults_too():
    r = _recon()
    h = hashed_recon(r, ("barycentric", "mc"))
    assert h["mc"] == r["mc"] and "mcir" not in h
    # a default that changes (as the registration did) changes the key of a run at the defaults
    changed = dict(r, mc=dict(r["mc"], registration="lucas_kanade"))
    assert r["mc"]["registration"] != "lucas_kanade"
    assert hashed_recon(changed, ("barycentric", "mc")) != h


def test_mcir_reads_mc_model_so_it_hashes_both():
    r = _recon()
    h = hashed_recon(r, ("barycentric", "mc", "mcir"))
    assert h["mc"] == r["mc"] and h["mcir"] == r["mcir"]
    assert "mc" in hashed_recon(r, ("barycentric", "mcir"))


def test_keys_added_later_stay_out_at_their_fixed_defaults():
    r = _recon()
    assert "truth_free" not in hashed_recon(dict(r, truth_free=False), ("barycentric",))
    assert hashed_recon(dict(r, truth_free=True), ("barycentric",))["truth_free"] is True
