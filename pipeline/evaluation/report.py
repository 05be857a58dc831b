"""The 16-to-64-beam evaluation's rows as a printed table, a per-scan comparison and a CSV file."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from .methods import NETWORK
from .scoring import NON_GROUND, REGIONS, VOXEL_SIZE, Row


def format_table(rows: list[Row], voxel: float = VOXEL_SIZE) -> str:
    """A plain-text table per region: scan, method, points, CD, HD, HD95 (metres), P, R, F1 (of
    occupied `voxel`-metre cubes)."""
    header = f"{'scan':<24} {'method':<20} {'points':>8} {'CD m':>8} {'HD m':>8} {'HD95 m':>8} " \
             f"{'P':>6} {'R':>6} {'F1':>6}"
    blocks = []
    for region in REGIONS:
        lines = [f"{region} region (vs the full 64-ring scan, voxels {voxel} m)", header, "-" * len(header)]
        for row in (r for r in rows if r.region == region):
            s = row.score
            lines.append(f"{row.scan:<24} {row.method:<20} {s.points:>8d} {s.chamfer:>8.4f} {s.hausdorff:>8.3f} "
                         f"{s.hd95:>8.3f} {s.precision:>6.3f} {s.recall:>6.3f} {s.f1:>6.3f}")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def per_scan_comparison(rows: list[Row], method: str = NETWORK, region: str = NON_GROUND) -> str:
    """On how many scans `method` beats each other method in `region`: lower Chamfer distance,
    higher voxel F1 (ties and NaN count as not better). The "mean" rows are left out.

    Returns:
        One line per other method, e.g. "  range-image linear   CD lower on 6/6   F1 higher on 4/6",
        under a heading; "" when `method` has no per-scan rows in `region`.
    """
    scores = {(r.scan, r.method): r.score for r in rows if r.region == region and r.scan != "mean"}
    scans = [scan for scan, name in scores if name == method]
    if not scans:
        return ""
    lines = [f"{method} against each method, {region} region, per scan"]
    for other in dict.fromkeys(name for _, name in scores if name != method):
        pairs = [(scores[scan, method], scores[scan, other]) for scan in scans if (scan, other) in scores]
        lower = sum(ours.chamfer < theirs.chamfer for ours, theirs in pairs)
        higher = sum(ours.f1 > theirs.f1 for ours, theirs in pairs)
        lines.append(f"  {other:<20} CD lower on {lower}/{len(pairs)}   F1 higher on {higher}/{len(pairs)}")
    return "\n".join(lines)


def write_record(record: dict, path: Path) -> Path:
    """Write a run's record (what made the CSV's rows: the input, the weights and their checksums,
    the settings, the scans left out) as JSON, atomically; returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    temporary.replace(path)
    return path


def write_csv(rows: list[Row], path: Path) -> Path:
    """Write the rows as CSV (columns: scan, method, region, points, chamfer, hausdorff, hd95,
    precision, recall, f1, seconds); returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0].as_dict()) if rows else ["scan"])
        writer.writeheader()
        writer.writerows(row.as_dict() for row in rows)
    temporary.replace(path)
    return path
