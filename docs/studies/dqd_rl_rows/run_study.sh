#!/usr/bin/env bash
# The five-row study (docs/studies/dqd_rl_rows/README.md): dqd-rl's five rows on QD Hopper as the
# preset sets them, 5 seeds, at the budget BUDGET (evaluations a run, chosen by the calibration
# below as README.md says), each final archive re-evaluated on 5 new resets (the primary metric's
# corrected archive), and the comparison against pga_me. Run from the repository's root, with
# requirements-learning.txt installed; everything goes to outputs/dqd_rl_rows/. An experiment
# stopped (Ctrl-C, a lost machine) goes on with: python lunar_lander.py resume FOLDER
set -euo pipefail
OUT=${OUT:-outputs/dqd_rl_rows}
STUDY=docs/studies/dqd_rl_rows
PLAN=docs/presets/dqd_rl_hopper.toml
if [ "${1:-}" = "calibrate" ]; then  # seed 101 (no study seed), each row, 4,000 evaluations, timed
  began=$(date +%s)
  mkdir -p "$OUT"  # its progress lines (which show its scores) to a log: only its time is read
  python lunar_lander.py experiment --plan "$PLAN" --seeds 101 --evaluations 4000 --pictures false \
    --workers 2 --outdir "$OUT/calibration" > "$OUT/calibration.log" 2>&1
  took=$(( $(date +%s) - began ))
  # 5 seeds at B evaluations take ~5 B / 4000 times as long: the most thousands that fit in 2 h
  echo "calibration: $took s; BUDGET=$(( 7200 * 4000 / (5 * took) / 1000 * 1000 ))"
  exit 0
fi
BUDGET=${BUDGET:?set BUDGET to the number the calibration prints (README.md)}
python lunar_lander.py experiment --plan "$PLAN" --evaluations "$BUDGET" --pictures false --workers 2 --outdir "$OUT/study"
python lunar_lander.py evaluate "$OUT/study" --corrected --repeats 5 --workers 2
python lunar_lander.py compare "$OUT/study" --corrected --baseline pga_me --out "$STUDY/rows_corrected.png" --overwrite
python lunar_lander.py compare "$OUT/study" --baseline pga_me --out "$STUDY/rows_own.png" --overwrite
