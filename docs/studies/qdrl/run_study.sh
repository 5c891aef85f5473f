#!/usr/bin/env bash
# The QD-RL study (docs/studies/qdrl/README.md): four algorithms with an MLP policy, and the best of
# them with the linear policy, on HalfCheetah-v5's foot contacts, 5 seeds each, at one budget of
# evaluations. Run from the repository's root; its experiments go to outputs/qdrl/ (BUDGET:
# evaluations per run, 16000 by default; about 50 minutes on 2 cores).
set -euo pipefail
BUDGET=${BUDGET:-16000}
OUT=${OUT:-outputs/qdrl}
COMMON=(--env HalfCheetah-v5 --episode_length 100 --grid 32 --seeds 1-5 --evaluations "$BUDGET" --workers 2)
MLP=(--policy mlp --hidden 32,32)
run() { python lunar_lander.py experiment "${COMMON[@]}" --outdir "$OUT/$1" "${@:2}"; }
# dqd-rl's CMA-MEGA (ES): one emitter, 100 mirrored samples at 0.02, 99 branched solutions
run cma_mega_es --algorithms cma_mega_es "${MLP[@]}" --n_emitters 1 --batch_size 99 --es_samples 100 --es_sigma 0.02 --sigma0 1.0
run cma_maega_es --algorithms cma_maega_es "${MLP[@]}" --n_emitters 1 --batch_size 99 --es_samples 100 --es_sigma 0.02 --sigma0 1.0
# sep-CMA-MAE (Tjanaka et al. 2023) at sigma 0.02; MAP-Elites with QDax's iso+line steps (0.005, 0.05)
run sep_cma_mae --algorithms sep_cma_mae "${MLP[@]}" --n_emitters 5 --batch_size 40 --sigma0 0.02
run line_map_elites --algorithms line_map_elites "${MLP[@]}" --n_emitters 2 --batch_size 100 --sigma0 0.005 --line_sigma 0.05
# the best of them (the highest mean final QD score, unless LINEAR_ROW names one), with the linear policy
LINEAR_ROW=${LINEAR_ROW:-$(python - "$OUT" <<'PY'
import json, pathlib, statistics, sys
rows = ("cma_mega_es", "cma_maega_es", "sep_cma_mae", "line_map_elites")
score = {row: statistics.mean(json.loads(m.read_text())[-1]["qd_score"]
                              for m in pathlib.Path(sys.argv[1], row).glob("*/metrics.json")) for row in rows}
print(max(score, key=score.get))
PY
)}
if [ -n "$LINEAR_ROW" ]; then
  case "$LINEAR_ROW" in
    cma_mega_es|cma_maega_es) FLAGS=(--n_emitters 1 --batch_size 99 --es_samples 100 --es_sigma 0.02 --sigma0 1.0) ;;
    sep_cma_mae) FLAGS=(--n_emitters 5 --batch_size 40 --sigma0 0.02) ;;
    line_map_elites) FLAGS=(--n_emitters 2 --batch_size 100 --sigma0 0.005 --line_sigma 0.05) ;;
  esac
  run "${LINEAR_ROW}_linear" --algorithms "$LINEAR_ROW" --policy linear "${FLAGS[@]}"
fi
