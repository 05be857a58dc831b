"""`python -m pipeline ARGS` runs the `kitti-pu` command line (`pipeline.entry`)."""

from .entry import main

main()
