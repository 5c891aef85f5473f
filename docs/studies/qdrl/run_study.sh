#!/usr/bin/env bash
# The QD-RL study (docs/studies/qdrl/README.md): its plan (plan.toml: 4 rows x 5 seeds, 16,000
# evaluations a run), each final archive re-evaluated on 5 new resets (the primary metric's
# corrected archive), and the two comparisons the README reports. Run from the repository's root;
# everything goes to outputs/qdrl/ (on 2 cores, 2026-12-04: about 21 minutes for the first
# question, 18 for the second).
set -euo pipefail
OUT=${OUT:-outputs/qdrl}
STUDY=docs/studies/qdrl
python lunar_lander.py experiment --plan "$STUDY/plan.toml" --workers 2 --outdir "$OUT/study"
python lunar_lander.py evaluate "$OUT/study" --corrected --repeats 5 --workers 2
python lunar_lander.py compare "$OUT/study" --corrected --baseline cma_mega_es --out "$STUDY/qdrl_corrected.png" --overwrite
python lunar_lander.py compare "$OUT/study" --baseline cma_mega_es --out "$STUDY/qdrl_own.png" --overwrite
# The second question: the linear policy against the network (forms.toml: each form's step size
# chosen on tuning seeds by its mean final QD score, then the 5 study seeds at the whole budget).
python lunar_lander.py experiment --plan "$STUDY/forms.toml" --workers 2 --outdir "$OUT/tuning"
best() { python - "$OUT/tuning" "$1" <<'PY'
import json, pathlib, statistics, sys
runs = [json.loads((run / "config.json").read_text()) | {"qd": json.loads((run / "metrics.json").read_text())[-1]["qd_score"]}
        for run in pathlib.Path(sys.argv[1]).iterdir() if (run / "metrics.json").is_file()]
mine = [run for run in runs if run["policy"] == sys.argv[2]]
sigmas = sorted({run["sigma0"] for run in mine})
print(max(sigmas, key=lambda s: statistics.mean(run["qd"] for run in mine if run["sigma0"] == s)))
PY
}
FORM=(--env HalfCheetah-v5 --episode_length 100 --grid 32 --start glorot --reset each --algorithms sep_cma_mae
      --n_emitters 5 --batch_size 40 --seeds 1-5 --evaluations 16000 --pictures false --workers 2)
python lunar_lander.py experiment "${FORM[@]}" --policy linear --sigma0 "$(best linear)" --outdir "$OUT/linear"
python lunar_lander.py experiment "${FORM[@]}" --policy mlp --hidden 32,32 --sigma0 "$(best mlp)" --outdir "$OUT/mlp"
for form in linear mlp; do python lunar_lander.py evaluate "$OUT/$form" --corrected --repeats 5 --workers 2; done
python lunar_lander.py compare "$OUT/linear" "$OUT/mlp" --corrected --out "$STUDY/forms_corrected.png" --overwrite
