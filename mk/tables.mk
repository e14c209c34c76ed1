# The paper's Table 1 on data-se (benchmarks/table1.py): visual hull, L1 concatenation and L2 dense
# back-projection baselines (stages/baselines, shipped weights stages/weights/baseline_*.pt), L7 (SBP with
# uniform poses, stages/weights/sbp_uniform.pt) and L8 (stages/weights/sbp.pt); rows whose weights are
# missing show "not available". Per-case results are cached in $(OUT)/table1/ (keyed by weights + data),
# so a second run only re-assembles docs/TABLE1.md and docs/table1/*.json.
# TABLE1_ARGS passes options through, e.g. TABLE1_ARGS="--limit 10".
# train-baselines retrains both baselines (resumable; BASELINE_*_STEPS set the run lengths).

TABLE1_THREADS ?= 2
TABLE1_ARGS ?=
BASELINE_DENSE_STEPS ?= 1800
BASELINE_CONCAT_STEPS ?= 4000

.PHONY: reproduce-table1 train-baselines

reproduce-table1: data-se  ## Table 1 on data-se, every configuration -> docs/TABLE1.md (+ docs/table1/*.json)
	OMP_NUM_THREADS=$(TABLE1_THREADS) $(PY) benchmarks/table1.py --threads $(TABLE1_THREADS) $(TABLE1_ARGS)

train-baselines: train-cases  ## retrain the Table 1 baselines -> stages/weights/baseline_{dense,concat}.pt
	for m in dense:$(BASELINE_DENSE_STEPS) concat:$(BASELINE_CONCAT_STEPS); do \
	  arch=$${m%%:*}; steps=$${m##*:}; \
	  if [ -f $(OUT)/baselines/$$arch/checkpoint.pt ]; then resume=--resume; else resume=; fi; \
	  OMP_NUM_THREADS=1 $(PY) -m stages.baselines.train --model $$arch --steps $$steps --threads 1 \
	    --out $(OUT)/baselines/$$arch --ship $$resume || exit 1; \
	done
