"""Issue 19 item 6 (docs/results/table2-pitch-0.02.md "Table 2 at pitch 0.02"): share of each method's
interpolation weight (sum |w|) on turns beyond the SSRB-exact window, one slice (55) of paper-p002, pitch 0.02, candidate window 28 mm; all 50 targets."""
import numpy as np

from clrecon.config.scene import load_scene
from clrecon.pipeline.run import resolve_targets
from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.interpolation import weights as ip
from clrecon.scan import table as geometry

s = load_scene("paper-p002").replace(recon={"candidate_window_mm": 28.0})
cfg = reconstruct.ReconstructionConfig.from_scene(s)
table = geometry.projection_table(s, 0.02)
ptab, _ = geometry.usable_table(s, table)
z = reconstruct.slice_positions(s)[55:56]
w_exact = rebin.slice_window_mm(s.scanner, cfg.object_radius_mm)
g = rebin.candidate_groups(ptab, z, s.scanner, cfg.object_radius_mm, 28.0)
t = resolve_targets(s)
tg = np.asarray(t.pairs)
c, a = ptab.cardiac_phase[g.row], ptab.resp_amplitude[g.row]
far = np.abs(g.dz_mm) > w_exact + 1e-9
print(f"SSRB-exact window {w_exact:.2f} mm; candidates per view {np.median(np.diff(g.offsets)):.0f}, beyond it {far.mean():.1%}")
opts = reconstruct.weight_options(cfg, t)
for m in ("barycentric", "local_linear", "nearest"):
    W = ip.batch_weights(m, c, a, g.offsets, tg, dz=g.dz_mm, **opts)
    aw = np.abs(W.weight)
    print(f"{m:13s} share of |weight| on turns beyond {w_exact:.1f} mm: {(aw * far[W.index]).sum() / aw.sum():.1%}")
