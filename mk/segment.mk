# 2D vessel segmenter (stages/segment): simulated training frames under data/seg, then training on one
# thread in two resumable stages, each with its checkpoint and log:
#   1. from scratch, 6000 steps (out/seg/ckpt.pt, out/seg/train.log) -> out/seg/base.pt;
#   2. fine-tuning from it at a lower learning rate, partially filled frames drawn 3x as often
#      (out/seg_ft/ckpt.pt, out/seg_ft/train.log) -> the shipped stages/weights/seg.pt.
# SEG_MINUTES / SEG_FT_MINUTES cap the two stages' wall time.

SEG_MINUTES ?= 40
SEG_FT_MINUTES ?= 35

.PHONY: train-seg seg-data

seg-data: install  ## render the segmenter's simulated training/test frames (data/seg, training seeds only)
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.data test train

train-seg: seg-data  ## train the 2D vessel segmenter -> stages/weights/seg.pt (resumable, 1 thread)
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.train --minutes $(SEG_MINUTES) --steps 6000 \
		--ckpt $(OUT)/seg/ckpt.pt --weights $(OUT)/seg/base.pt
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.train --init $(OUT)/seg/base.pt --minutes $(SEG_FT_MINUTES) \
		--steps 3000 --lr 1e-3 --partial-weight 3 --ckpt $(OUT)/seg_ft/ckpt.pt
