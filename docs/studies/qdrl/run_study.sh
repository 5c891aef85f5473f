#!/usr/bin/env bash
# The QD-RL study (docs/studies/qdrl/README.md): its plan (plan.toml: 4 rows x 5 seeds, 16,000
# evaluations a run), each final archive re-evaluated on 5 new resets (the primary metric's
# corrected archive), and the two comparisons the README reports. Run from the repository's root;
# everything goes to outputs/qdrl/ (about 50 minutes on 2 cores, 2026-12-04).
set -euo pipefail
OUT=${OUT:-outputs/qdrl}
STUDY=docs/studies/qdrl
python lunar_lander.py experiment --plan "$STUDY/plan.toml" --workers 2 --outdir "$OUT/study"
python lunar_lander.py evaluate "$OUT/study" --corrected --repeats 5 --workers 2
python lunar_lander.py compare "$OUT/study" --corrected --baseline cma_mega_es --out "$STUDY/qdrl_corrected.png" --overwrite
python lunar_lander.py compare "$OUT/study" --baseline cma_mega_es --out "$STUDY/qdrl_own.png" --overwrite
