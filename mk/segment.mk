# 2D vessel segmenter (stages/segment): simulated training frames under data/seg, then training on one
# thread (resumable: out/seg/ckpt.pt; log out/seg/train.log); writes the shipped stages/weights/seg.pt.
# SEG_MINUTES caps the training wall time.

SEG_MINUTES ?= 40

.PHONY: train-seg seg-data

seg-data: install  ## render the segmenter's simulated training/test frames (data/seg, training seeds only)
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.data test train

train-seg: seg-data  ## train the 2D vessel segmenter -> stages/weights/seg.pt (resumable, 1 thread)
	mkdir -p $(OUT)/seg
	OMP_NUM_THREADS=1 $(PY) -m stages.segment.train $(SEG_MINUTES)
