"""`python -m pipeline ARGS` runs the `kitti-pu` command line (`pipeline.cli`)."""

from .cli import main

main()
