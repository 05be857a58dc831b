"""The synthetic data CAD-PU trains and is tested on: procedural meshes (`shapes`), procedural
streets (`street`) and a simulated rotating LiDAR that scans them in KITTI's point order (`lidar`)."""
