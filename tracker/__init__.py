"""Association and tracking against a terrain prior, in subpackages that follow the data flow: types →
models → integrate / gating → association → io → run → study, with the command line in :mod:`tracker.cli`.
The terrain is known only through :mod:`pipeline.prior`."""
