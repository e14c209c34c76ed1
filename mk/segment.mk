# 2D vessel segmenter (stages/segment): simulated training frames under data/seg, then training on one
# thread (resumable: out/seg/ckpt.pt; log out/seg/train.log); writes the shipped stages/weights/seg.pt.
# SEG_MINUTES caps the training wall time. Fine-tuning from existing weights:
#   python -m stages.segment.train --init stages/weights/seg.pt --lr 1e-3 --partial-weight 3 \
#       --ckpt out/seg_ft/ckpt.pt --weights out/seg_ft/seg.pt
# (tried for #8: 888 steps did not beat the shipped weights, which stay the from-scratch run below).

SEG_MINUTES ?= 40

.PHONY: train-seg seg-data

seg-data: install  ## render the segmenter's simulated training/test frames (data/seg, training seeds only)
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.data test train

train-seg: seg-data  ## train the 2D vessel segmenter -> stages/weights/seg.pt (resumable, 1 thread)
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.train --minutes $(SEG_MINUTES) --steps 6000 --ckpt $(OUT)/seg/ckpt.pt
