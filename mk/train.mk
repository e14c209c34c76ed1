# SBP network (stages/sbp, stages/train.py): procedural training cases (seeds 0–59, two trees each,
# never the data-se/data-re/example seeds), then online-rendered training, resumable from
# $(OUT)/train_sbp/checkpoint.pt; the final weights become the shipped stages/weights/sbp.pt.
# SBP_STEPS sets the length of the run; SBP_THREADS the torch threads (1 is fastest on a busy machine).
# The shipped weights had two more stages, each from the previous stage's weights with a fresh optimiser
# and a new pair order: SBP_FINETUNE_STEPS at peak lr 1e-3, seed 7 in $(OUT)/train_sbp2, then
# SBP_FINETUNE2_STEPS at peak lr 5e-4, seed 11 in $(OUT)/train_sbp3, then SBP_FINETUNE3_STEPS at peak
# lr 3e-4, seed 13 in $(OUT)/train_sbp4, then SBP_FINETUNE4_STEPS at peak lr 2e-4, seed 19 in
# $(OUT)/train_sbp5 (0: stop before that stage).

SBP_CASES ?= 60
SBP_STEPS ?= 1300
SBP_THREADS ?= 1
SBP_FINETUNE_STEPS ?= 1000
SBP_FINETUNE2_STEPS ?= 1200
SBP_FINETUNE3_STEPS ?= 1000
SBP_FINETUNE4_STEPS ?= 800

.PHONY: train train-cases

train-cases: data/train_cases/.done  ## prepare the SBP training cases once (data/train_cases)

data/train_cases/.done: | install
	$(AUTOCAR) prep-ct --synthetic $(SBP_CASES) --seed 0 -o data/train_cases --jobs 2 --no-preview
	touch $@

train: train-cases  ## train the SBP network -> stages/weights/sbp.pt (resumes an interrupted run)
	if [ -f $(OUT)/train_sbp/checkpoint.pt ]; then resume=--resume; else resume=; fi; \
	$(AUTOCAR) train data/train_cases -o $(OUT)/train_sbp --steps $(SBP_STEPS) --threads $(SBP_THREADS) $$resume
	if [ "$(SBP_FINETUNE_STEPS)" = 0 ]; then cp $(OUT)/train_sbp/model.pt stages/weights/sbp.pt; exit 0; fi; \
	if [ -f $(OUT)/train_sbp2/checkpoint.pt ]; then resume=--resume; else resume="--init $(OUT)/train_sbp/model.pt"; fi; \
	$(AUTOCAR) train data/train_cases -o $(OUT)/train_sbp2 --steps $(SBP_FINETUNE_STEPS) --lr 1e-3 --seed 7 \
	  --val-every 0 --threads $(SBP_THREADS) $$resume
	if [ "$(SBP_FINETUNE_STEPS)" = 0 ]; then exit 0; fi; \
	if [ "$(SBP_FINETUNE2_STEPS)" = 0 ]; then cp $(OUT)/train_sbp2/model.pt stages/weights/sbp.pt; exit 0; fi; \
	if [ -f $(OUT)/train_sbp3/checkpoint.pt ]; then resume=--resume; else resume="--init $(OUT)/train_sbp2/model.pt"; fi; \
	$(AUTOCAR) train data/train_cases -o $(OUT)/train_sbp3 --steps $(SBP_FINETUNE2_STEPS) --lr 5e-4 --seed 11 \
	  --val-every 0 --threads $(SBP_THREADS) $$resume
	if [ "$(SBP_FINETUNE_STEPS)" = 0 ] || [ "$(SBP_FINETUNE2_STEPS)" = 0 ]; then exit 0; fi; \
	if [ "$(SBP_FINETUNE3_STEPS)" = 0 ]; then cp $(OUT)/train_sbp3/model.pt stages/weights/sbp.pt; exit 0; fi; \
	if [ -f $(OUT)/train_sbp4/checkpoint.pt ]; then resume=--resume; else resume="--init $(OUT)/train_sbp3/model.pt"; fi; \
	$(AUTOCAR) train data/train_cases -o $(OUT)/train_sbp4 --steps $(SBP_FINETUNE3_STEPS) --lr 3e-4 --seed 13 \
	  --val-every 0 --threads $(SBP_THREADS) $$resume
	if [ "$(SBP_FINETUNE_STEPS)" = 0 ] || [ "$(SBP_FINETUNE2_STEPS)" = 0 ] || [ "$(SBP_FINETUNE3_STEPS)" = 0 ]; then exit 0; fi; \
	if [ "$(SBP_FINETUNE4_STEPS)" = 0 ]; then cp $(OUT)/train_sbp4/model.pt stages/weights/sbp.pt; exit 0; fi; \
	if [ -f $(OUT)/train_sbp5/checkpoint.pt ]; then resume=--resume; else resume="--init $(OUT)/train_sbp4/model.pt"; fi; \
	$(AUTOCAR) train data/train_cases -o $(OUT)/train_sbp5 --steps $(SBP_FINETUNE4_STEPS) --lr 2e-4 --seed 19 \
	  --val-every 0 --threads $(SBP_THREADS) $$resume && cp $(OUT)/train_sbp5/model.pt stages/weights/sbp.pt
