# The paper's Table 1 on data-se (benchmarks/table1.py): visual hull, L1 concatenation and L2 dense
# back-projection baselines (stages/baselines, shipped weights stages/weights/baseline_*.pt), L7 (SBP with
# uniform poses, stages/weights/sbp_uniform.pt) and L8 (stages/weights/sbp.pt); rows whose weights are
# missing show "not available". Per-case results are cached in $(OUT)/table1/ (keyed by weights + data),
# so a second run only re-assembles docs/TABLE1.md and docs/table1/*.json.
# TABLE1_ARGS passes options through, e.g. TABLE1_ARGS="--limit 10".
# reproduce-table2 (benchmarks/table2.py): data-re end to end from DICOM for the visual hull, L2, L7, L8 and
# L8 without graph optimisation, plus the held-out-view table on the real phantom runs (../shared), in
# TABLE2_JOBS worker processes; reconstructions are cached in $(OUT)/table2/<row>/<case>/ (keyed by the
# runs and every weights file), so a second run only re-scores -> docs/TABLE2.md (+ docs/table2/*.json).
# TABLE1_ARGS=--reuse-docs / TABLE2_ARGS=--reuse-docs also take a row from its committed per-case JSON in
# docs/table1|2/ when it was computed from the same inputs (weights, data, pipeline), so a fresh clone
# recomputes only the rows whose weights changed; without it every row is computed (or taken from out/).
# train-baselines retrains both baselines (resumable; BASELINE_*_STEPS set the run lengths).

TABLE1_THREADS ?= 2
TABLE1_ARGS ?=
TABLE2_JOBS ?= 2
TABLE2_ARGS ?=
BASELINE_DENSE_STEPS ?= 1800
BASELINE_CONCAT_STEPS ?= 4000

.PHONY: reproduce-table1 reproduce-table2 train-baselines

reproduce-table1: data-se  ## Table 1 on data-se, every configuration -> docs/TABLE1.md (+ docs/table1/*.json)
	OMP_NUM_THREADS=$(TABLE1_THREADS) $(PY) benchmarks/table1.py --threads $(TABLE1_THREADS) $(TABLE1_ARGS)

reproduce-table2: data-re  ## Table 2 on data-re (VH, L2, L7, L8, L8 no graph-opt) + phantom held-out table -> docs/TABLE2.md
	OMP_NUM_THREADS=1 $(PY) benchmarks/table2.py --jobs $(TABLE2_JOBS) $(TABLE2_ARGS)

train-baselines: train-cases  ## retrain the Table 1 baselines -> stages/weights/baseline_{dense,concat}.pt
	for m in dense:$(BASELINE_DENSE_STEPS) concat:$(BASELINE_CONCAT_STEPS); do \
	  arch=$${m%%:*}; steps=$${m##*:}; \
	  if [ -f $(OUT)/baselines/$$arch/checkpoint.pt ]; then resume=--resume; else resume=; fi; \
	  OMP_NUM_THREADS=1 $(PY) -m stages.baselines.train --model $$arch --steps $$steps --threads 1 \
	    --out $(OUT)/baselines/$$arch --ship $$resume || exit 1; \
	done
