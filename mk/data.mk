# Data products of the synthetic X-ray engine (stages/render/products.py). Deterministic from seeds:
# data-se 1 000 000+, data-re 2 000 000+, examples 3 000 000 (training seeds stay below 1 000 000).
# Each rule is cheap when its manifest is up to date (the command itself skips, exit 0). Otherwise --resume
# continues in the existing folder (the output policy refuses a non-empty folder without --force or
# --resume): prepared cases and data-re's finished cases are kept, the rest made; an interrupted rule
# continues where it stopped. `autocar render se --out data/se --force` rebuilds from nothing.

.PHONY: data-se data-re examples

data-se: install  ## synthetic evaluation set for Table 1: 90 trees, one static two-view pair each (data/se)
	$(AUTOCAR) render se --out data/se --resume

data-re: install  ## real-world-like set for Table 2: 21 dynamic cases, two XA runs each (data/re)
	$(AUTOCAR) render re --out data/re --resume

examples: install  ## regenerate the bundled example (examples/run_a.dcm, run_b.dcm, truth.zarr)
	$(AUTOCAR) render example --out examples --resume
