"""The 16-to-64-beam evaluation on real scans (`kitti-pu eval-kitti`): `kitti` runs it, `methods`
densifies a thinned scan with each method compared, `scoring` scores an output against the full
scan (metrics from `cadpu.metrics`), `report` prints and writes the rows, `figure` draws a scan."""
