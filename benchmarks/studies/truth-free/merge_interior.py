import glob
import json

from benchmarks.truth_free_trust import analyse

I = json.load(open("benchmarks/studies/truth-free/interior.json"))
cases = []
for f in sorted(glob.glob("benchmarks/studies/truth-free/case-*.json")):
    c = json.load(open(f))
    for r in c["rows"]:
        e = I["cases"][f"{c['case']}/{r['pitch']}"]["errors"][r["variant"]]["interior"][r["kernel"]]
        for reg in ("row", "heart"):
            r[f"cv_interior_{reg}"] = e[reg]["rms_hu_mm"]
            r[f"cv_interior_{reg}_raw"] = e[reg]["rms_raw_hu_mm"]
    cases.append(c)
print({k: (v["folds"], v["seconds"]["total"]) for k, v in I["cases"].items()}, I["load"], I["date"])
keys = [
    "small:interior:heart",
    "small:loto:heart",
    "small:nndm:heart",
    "small:loto:img_small",
    "large:interior:row",
    "large:loto:row",
    "large:loto:img_large",
]
print("| configurations | n | " + " | ".join(keys) + " |\n|---|---|" + "---|" * len(keys))
byname = {c["case"]: c for c in cases}
for label, names in (
    ("all three scenes", list(byname)),
    ("demo", ["demo"]),
    ("demo-hrv (held out)", ["demo-hrv"]),
    ("paper-p010 slab", ["paper-p010"]),
):
    an = analyse([byname[n] for n in names])
    print(
        f"| {label} | {an['n_configurations']} | "
        + " | ".join(f"{an['spearman'].get(k, float('nan')):.2f}" for k in keys)
        + " |"
    )
an = analyse(cases)
print("\nwithin case")
ks = ["small:interior:heart", "small:nndm:heart", "large:interior:row", "large:nndm:row"]
print("| case | " + " | ".join(ks) + " |\n|---|" + "---|" * len(ks))
for ck in sorted(an["spearman_within_case"]["small:interior:heart"]):
    print(f"| {ck} | " + " | ".join(f"{an['spearman_within_case'][k][ck]:.2f}" for k in ks) + " |")
print("\nselection by interior")
print(
    "| case | pitch | variant | FOV | reference | interior choice | its MAE | gain % | nndm choice gain % | oracle gain % |\n|---|---|---|---|---|---|---|---|---|---|"
)
for e in an["selection"]:
    for fov, r1 in (("small", "heart"), ("large", "row")):
        print(
            f"| {e['case']} | {e['pitch'][1:]} | {e['variant']} | {fov} | {e[f'{fov}:best_of_bary_ll']:.2f} | {e[f'{fov}:interior:{r1}:choice']} | {e[f'{fov}:interior:{r1}:mae']:.2f} | {e[f'{fov}:interior:{r1}:gain_pct']:+.1f} | {e[f'{fov}:nndm:{r1}:gain_pct']:+.1f} | {e[f'{fov}:oracle_gain_pct']:+.1f} |"
        )
