"""Compare TUM trajectories with a bag's ground truth (evo: ATE after Sim(3), RPE) and plot.

    python -m rsvo_ros.tools.compare BAG NAME=TRAJ.tum [NAME=TRAJ.tum ...] [--plot OUT.png]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rsvo_ros.ros import bagio
from rsvo_ros.ros.convert import stamp_ns
from rsvo_ros.tools.replay import accuracy, ground_truth_of, sim3_aligned_positions


def read_tum(path: Path) -> dict[int, np.ndarray]:
    poses = {}
    for line in Path(path).read_text().splitlines():
        v = [float(x) for x in line.split()]
        if len(v) != 8:
            continue
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(v[4:8]).as_matrix()
        T[:3, 3] = v[1:4]
        poses[round(v[0] * 1e9)] = T
    return poses


def read_ground_truth(bag: Path, topic: str = bagio.GROUND_TRUTH_TOPIC) -> dict[int, np.ndarray]:
    gt = {}
    with bagio.BagReader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _t, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            gt[stamp_ns(msg.header)] = ground_truth_of(msg, conn.msgtype)[0]
    return gt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.compare", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path)
    p.add_argument("trajectories", nargs="+", metavar="NAME=TRAJ.tum")
    p.add_argument("--plot", type=Path, default=None)
    args = p.parse_args(argv)
    gt = read_ground_truth(args.bag)
    if not gt:
        print(f"compare: no ground truth in {args.bag}", file=sys.stderr)
        return 1
    rows = []
    for item in args.trajectories:
        name, _, path = item.partition("=")
        est = read_tum(Path(path))
        if len(est) < 3:
            print(f"{name:>6}: only {len(est)} poses in {path}")
            continue
        acc = accuracy(gt, est)
        rows.append((name, est, acc))
        print(f"{name:>6}: {len(est):4d} poses, ATE {acc['ate_m']['rmse']:.3f} m RMSE "
              f"(Sim(3)), RPE {acc['rpe_trans_m']['rmse']:.3f} m / "
              f"{acc['rpe_rot_deg']['rmse']:.2f} deg per frame")
    if args.plot and rows:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 6))
        g = np.array([gt[s][:3, 3] for s in sorted(gt)])
        ax.plot(g[:, 0], g[:, 2], "k-", lw=2, label="ground truth")
        for (name, est, acc), color in zip(rows, ("tab:red", "tab:blue", "tab:green"),
                                           strict=False):
            _, xyz = sim3_aligned_positions(gt, est)
            ax.plot(xyz[:, 0], xyz[:, 2], "-", color=color,
                    label=f"{name} (ATE {acc['ate_m']['rmse']:.3f} m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.grid(True, alpha=0.3)
        ax.legend()
        ax.set_title("live rsvo_node odometry vs ground truth (Sim(3)-aligned, top view)")
        fig.tight_layout()
        fig.savefig(args.plot, dpi=100)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
