#!/usr/bin/env python3
"""Queries a map with one image and draws it beside its top matches into a PNG (OpenCV).

    PYTHONPATH=build/client/python python3 client/python/examples/query_and_draw.py \
        /work/shared/data/rtabmap-loop/60.jpg --map loop \
        --folder /work/shared/data/rtabmap-loop --top-k 3 --out matches.png

The server stores features, not images: a match's picture is found in --folder, the folder
replay_folder.py ingested (a place's sequence is its file's position there). Each match is
labelled with its place id, score and inliers, and shows the static keypoints the map stored for
it (green); needs Debian's python3-opencv.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List

import cv2
import numpy as np
from replay_folder import add_connection_flags, client_from, image_files

import placedb

HEIGHT = 360  # every panel is scaled to this height


def panel(image: np.ndarray, lines: List[str], keypoints: np.ndarray | None = None) -> np.ndarray:
    """``image`` scaled to HEIGHT with ``keypoints`` (x, y rows) drawn and ``lines`` on top."""
    scale = HEIGHT / image.shape[0]
    out = cv2.resize(image, (round(image.shape[1] * scale), HEIGHT))
    if keypoints is not None:
        for x, y in keypoints[:, :2] * scale:
            cv2.circle(out, (int(x), int(y)), 2, (0, 200, 0), 1, cv2.LINE_AA)
    for i, line in enumerate(lines):
        origin = (8, 24 + 24 * i)
        cv2.putText(out, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1,
                    cv2.LINE_AA)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image", type=Path, help="the query image (JPEG / PNG)")
    parser.add_argument("--map", required=True)
    parser.add_argument("--folder", type=Path, required=True,
                        help="the folder replay_folder.py ingested")
    parser.add_argument("--top-k", type=int, default=3)
    parser.add_argument("--verify", action="store_true", help="verified matches only")
    parser.add_argument("--out", type=Path, default=Path("matches.png"))
    add_connection_flags(parser)
    args = parser.parse_args()

    query_image = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
    if query_image is None:
        print(f"cannot read {args.image}", file=sys.stderr)
        return 1
    files = image_files(args.folder)
    try:
        with client_from(args) as client:
            # The decoded BGR array goes as raw pixels (cv2's own layout).
            answer = client.query(args.map, query_image, top_k=args.top_k, verify=args.verify)
            panels = [panel(query_image, [f"query {args.image.name}",
                                          f"{answer.counts.kept} static features"])]
            for rank, match in enumerate(answer.matches, 1):
                place = client.get_place(args.map, match.place_id, include_features=True)
                if match.sequence >= len(files):
                    print(f"place {match.place_id}: sequence {match.sequence} is not a file of "
                          f"{args.folder}", file=sys.stderr)
                    continue
                image = cv2.imread(str(files[match.sequence]), cv2.IMREAD_COLOR)
                lines = [f"#{rank} place {match.place_id} ({files[match.sequence].name})",
                         f"score {match.score:.3f}",
                         f"inliers {match.inliers}" + (" verified" if match.verified else "")]
                panels.append(panel(image, lines, place.keypoints))
    except placedb.Error as e:
        print(f"query_and_draw: {e}", file=sys.stderr)
        return 1
    if not answer.matches:
        print("no matches" + (f" ({answer.rejection})" if answer.rejection else ""))
    if not cv2.imwrite(str(args.out), np.hstack(panels)):
        print(f"cannot write {args.out}", file=sys.stderr)
        return 1
    print(f"{args.out}: the query and {len(panels) - 1} matches")
    for match in answer.matches:
        print(f"  place {match.place_id}  score {match.score:.4f}  inliers {match.inliers}  "
              f"agent {match.agent_id}  sequence {match.sequence}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
