"""Fit every point cloud in a directory on a Dask cluster and print one table.

    python examples/python/batch_dask.py CLOUDS_DIR [--scheduler tcp://HOST:8786] [--workers 2]
        [--global-only] [--out table.jsonl]

Without --scheduler it starts a LocalCluster of --workers processes on this machine; with it, the
same code runs on any cluster (dask-scheduler and dask-worker on each machine, each with
`pip install ./python` done). Each task reads one file and fits it with deformable_sq.fit, which
releases the GIL, so one worker may also run several threads. The table has a row per file, in
sorted order, with the fields `dsq fit`'s JSON lines use.
"""

import argparse
import json
import sys
from pathlib import Path

import deformable_sq

FIELDS = ("a", "a1", "a2", "a3", "e1", "e2", "mean", "p95", "converged", "steps")


def fit_file(path: str, options: dict) -> dict:
    """One row: the fit of one file, or the one-line reason it could not be fitted."""
    try:
        result = deformable_sq.fit(deformable_sq.load_points(path), **options)
    except ValueError as e:
        return {"file": path, "error": str(e)}
    params = result.to_dict()
    row = {"file": path}
    for key in FIELDS:
        row[key] = params["residuals"][key] if key in ("mean", "p95") else params[key]
    return row


def fit_directory(directory: str, client, options: dict) -> list:
    """Every .ply and .obj file under `directory`, fitted on `client`'s cluster, in sorted order."""
    files = sorted(
        str(p) for p in Path(directory).iterdir() if p.suffix.lower() in (".ply", ".obj")
    )
    futures = client.map(fit_file, files, options=options, pure=False)
    return client.gather(futures)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("directory")
    parser.add_argument("--scheduler", help="a running cluster's address; a LocalCluster if none")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster processes")
    parser.add_argument("--global-only", action="store_true", help="pure superquadrics")
    parser.add_argument("--out", help="also write the table here, one JSON line a row")
    args = parser.parse_args(argv)

    from dask.distributed import Client, LocalCluster

    options = {"global_only": True} if args.global_only else {}
    if args.scheduler:
        client = Client(args.scheduler)
        cluster = None
    else:
        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True)
        client = Client(cluster)
    try:
        rows = fit_directory(args.directory, client, options)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    lines = [json.dumps(row, sort_keys=True) for row in rows]
    print("\n".join(lines))
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")
    return 2 if any("error" in row for row in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
