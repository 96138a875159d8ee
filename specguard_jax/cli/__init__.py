"""Command-line entry points: `specguard-train` / `python train.py` (cli.train) and `specguard-evaluate` /
`python evaluate.py` (cli.evaluate); each module's main(argv=None) returns the exit status."""
