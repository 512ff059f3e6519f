import glob
import json

from benchmarks.truth_free_trust import analyse

cases = {json.load(open(f))["case"]: json.load(open(f)) for f in glob.glob("benchmarks/studies/truth-free/case-*.json")}
keys = [
    "small:loto:heart",
    "small:nndm:heart",
    "small:nndm_c:heart",
    "small:loto:img_small",
    "small:nndm_c:img_small",
    "large:loto:row",
    "large:nndm:row",
    "large:nndm_c:row",
    "large:loto:img_large",
    "large:nndm_c:img_large",
]
print("| configurations | n | " + " | ".join(keys) + " |")
print("|---|---|" + "---|" * len(keys))
for label, names in (
    ("all three scenes", list(cases)),
    ("demo", ["demo"]),
    ("demo-hrv (held out)", ["demo-hrv"]),
    ("demo + demo-hrv", ["demo", "demo-hrv"]),
    ("paper-p010 slab", ["paper-p010"]),
):
    an = analyse([cases[n] for n in names])
    print(f"| {label} | {an['n_configurations']} | " + " | ".join(f"{an['spearman'][k]:.2f}" for k in keys) + " |")
