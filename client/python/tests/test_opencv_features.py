"""Precomputed features straight from OpenCV: cv2.ORB on an ORB map, cv2.SIFT on a SIFT map."""

from __future__ import annotations

from pathlib import Path
from typing import List

import cv2
import numpy as np

import placedb


def _gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert image is not None, path
    return image


def _ingest_and_query(client: placedb.Client, map_name: str, detector, paths: List[Path]) -> None:
    frames = []
    for path in paths:
        image = _gray(path)
        keypoints, descriptors = detector.detectAndCompute(image, None)
        frames.append(placedb.Frame(keypoints=keypoints, descriptors=descriptors, image=image))
    results = list(client.ingest(map_name, frames, agent_id="cv"))
    for r, frame in zip(results, frames):
        assert r.error is None, r.error
        assert r.stored, r.rejection
        assert r.counts.total == len(frame.keypoints)
    for r, frame in zip(results, frames):
        answer = client.query(map_name, frame, top_k=3)
        assert answer.matches[0].place_id == r.place_id
        assert answer.matches[0].score > answer.matches[1].score


def test_cv2_orb_features(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    client.create_map("cv-orb")
    _ingest_and_query(client, "cv-orb", cv2.ORB_create(1000), rtabmap_frames[0:40:8])


def test_cv2_sift_features(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    created = client.create_map("cv-sift", placedb.MapSettings(vocabulary="sift"))
    assert created.feature_type == "sift"
    sift = cv2.SIFT_create(500)
    _ingest_and_query(client, "cv-sift", sift, rtabmap_frames[0:40:8])
    # An up-sampled keypoint (OpenCV octave -1) goes as API octave 0, the others as octave + 1.
    image = _gray(rtabmap_frames[0])
    keypoints, descriptors = sift.detectAndCompute(image, None)
    octaves = {((k.octave & 0xFF) ^ 0x80) - 0x80 for k in keypoints}
    assert -1 in octaves  # OpenCV's SIFT up-samples first: the conversion is exercised
    place = client.get_place(
        "cv-sift", client.query("cv-sift", rtabmap_frames[0]).matches[0].place_id,
        include_features=True,
    )
    assert place.descriptors is not None and place.descriptors.shape[1] == 128
    assert place.keypoints is not None and place.keypoints[:, 5].min() >= 0
