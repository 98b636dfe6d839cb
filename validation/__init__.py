"""Validation tools that stand apart from ``ident``'s own model.

:mod:`validation.plantsim` is a second, independent telemetry generator: it models how
a real plant records (physics at 20 kHz, sensor noise, anti-alias filter and
decimation, offsets, drift, 16-bit quantisation) and writes recordings with a truth
sidecar, for validating the segmenter, the gap fit and the diagnosis.  It never uses
``ident.model`` or ``ident.fit``.
"""
