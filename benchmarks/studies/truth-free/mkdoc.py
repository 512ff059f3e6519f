import glob
import json

d = "benchmarks/studies/truth-free"
cases = [json.load(open(f)) for f in sorted(glob.glob(f"{d}/case-*.json"))]
from benchmarks.truth_free_trust import analyse

an = analyse(cases)
print("n configurations", an["n_configurations"])
for c in cases:
    print(
        c["case"],
        c["slices"],
        c["targets"],
        c["commit"],
        c["date_utc"],
        c["load_average"],
        {k: round(v) for k, v in c["seconds"].items()},
        c["folds"],
    )
    for pk, cfg in c["truth_free_config"].items():
        print(
            "  ",
            pk,
            cfg["nndm_median_radius"],
            cfg.get("nndm_c_median_radius"),
            len(cfg["slices_z_mm"]),
            cfg["view_step"],
        )
print("\n| measure (CV) | true MAE FOV | loto | nndm | nndm_c |\n|---|---|---|---|---|")
for fov, regs in (("small", ["heart", "heart_raw", "img_small"]), ("large", ["row", "row_raw", "img_large"])):
    for r in regs:
        print(
            f"| {r} | {fov} | "
            + " | ".join(
                f"{an['spearman'].get(f'{fov}:{s}:{r}', float('nan')):.2f}" for s in ("loto", "nndm", "nndm_c")
            )
            + " |"
        )
print("\nwithin case (small, heart / img_small), (large, row / img_large)")
cases_k = sorted(an["spearman_within_case"]["small:nndm:heart"])
print(
    "| case | "
    + " | ".join(
        f"{fov}:{s}:{r}"
        for fov, r in (("small", "heart"), ("small", "img_small"), ("large", "row"), ("large", "img_large"))
        for s in ("loto", "nndm", "nndm_c")
    )
    + " |"
)
for ck in cases_k:
    print(
        f"| {ck} | "
        + " | ".join(
            f"{an['spearman_within_case'].get(f'{fov}:{s}:{r}', {}).get(ck, float('nan')):.2f}"
            for fov, r in (("small", "heart"), ("small", "img_small"), ("large", "row"), ("large", "img_large"))
            for s in ("loto", "nndm", "nndm_c")
        )
        + " |"
    )
print("\nselection")
print(
    "| case | pitch | variant | FOV | best of bary/LL | CV choice (nndm heart/row) | its MAE | gain % | CV choice (nndm_c img) | MAE | gain % | oracle | oracle gain % |"
)
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for e in an["selection"]:
    for fov, r1, r2 in (("small", "heart", "img_small"), ("large", "row", "img_large")):
        print(
            f"| {e['case']} | {e['pitch'][1:]} | {e['variant']} | {fov} | {e[f'{fov}:best_of_bary_ll']:.2f} | {e.get(f'{fov}:nndm:{r1}:choice')} | {e.get(f'{fov}:nndm:{r1}:mae', float('nan')):.2f} | {e.get(f'{fov}:nndm:{r1}:gain_pct', float('nan')):+.1f} | {e.get(f'{fov}:nndm_c:{r2}:choice')} | {e.get(f'{fov}:nndm_c:{r2}:mae', float('nan')):.2f} | {e.get(f'{fov}:nndm_c:{r2}:gain_pct', float('nan')):+.1f} | {e[f'{fov}:oracle']} | {e[f'{fov}:oracle_gain_pct']:+.1f} |"
        )
print("\nwindows")
print("| case | pitch | variant | method | SSRB-exact L/S | 28 mm L/S |\n|---|---|---|---|---|---|")
for c in cases:
    for pk, byv in c["windows"].items():
        for v, bym in byv.items():
            for m, w in bym.items():
                print(
                    f"| {c['case']} | {pk[1:]} | {v} | {m} | {w['0']['large']:.2f} / {w['0']['small']:.2f} | {w['28']['large']:.2f} / {w['28']['small']:.2f} |"
                )
print("\nall rows")
print(
    "| case | pitch | variant | kernel | MAE L | MAE S | nndm heart | nndm_c img small | loto row |\n|---|---|---|---|---|---|---|---|---|"
)
for c in cases:
    for r in c["rows"]:
        print(
            f"| {r['case']} | {r['pitch'][1:]} | {r['variant']} | {r['kernel']} | {r['mae_large']:.2f} | {r['mae_small']:.2f} | {r['cv_nndm_heart']:.0f} | {r.get('cv_nndm_c_img_small', float('nan')):.1f} | {r['cv_loto_row']:.0f} |"
        )
