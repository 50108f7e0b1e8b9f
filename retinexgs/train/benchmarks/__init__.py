"""Benchmarks that train (run through ``python -m retinexgs.bench proxy|retone|train-speed``): they belong to the
training layer because they drive the trainer and its losses; the reader benchmarks live in :mod:`retinexgs.bench`."""
