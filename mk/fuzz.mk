# DICOM fuzzing of the XA reader (issue 36): seeded mutations of the example runs through `autocar info`
# and the full read of `autocar reconstruct`; counts of tracebacks/hangs and peak memory -> docs.
FUZZ_CASES ?= 3000
FUZZ_SEED ?= 0

.PHONY: fuzz
fuzz: install  ## fuzz the DICOM reader (FUZZ_CASES=3000 seeded cases) -> docs/benchmarks/fuzz_dicom.md
	OMP_NUM_THREADS=1 $(PY) tests/fuzz_dicom.py --cases $(FUZZ_CASES) --seed $(FUZZ_SEED)
