"""The pipeline a user writes instead of starlog: the ``mcap`` reader, SEP and a filterpy UKF per star.

``tools/bench_pipeline.py`` times it beside ``starlog run`` on the same log (its ``user pipeline`` row): what
starlog's speed is worth against the libraries a star-tracker engineer would otherwise put together, each used as
its documentation shows, on one core:

* frames: ``mcap.reader.make_reader`` with ``mcap_protobuf``'s decoder factory (``foxglove.RawImage``);
* centroids: ``sep.Background``, ``sep.extract`` (1.5 sigma) and ``sep.winpos`` (the windowed position, sigma from
  ``sep.flux_radius`` as SExtractor sets it);
* tracks: one ``filterpy.kalman.UnscentedKalmanFilter`` per star, a static star with a small random walk (starlog's
  STATIC model), each detection given to the nearest predicted star within 3 px, a new filter for the others;
* output: every star's filtered position per frame, saved with ``numpy.savez`` at the end.

Usage::

    python tools/user_pipeline.py LOG OUT.npz [--topic /camera/image]
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the row is timed

import numpy as np
import sep
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

GATE_PX = 3.0
MEASUREMENT_SIGMA_PX = 0.05
RANDOM_WALK_PX = 0.01


def centroids(image: np.ndarray) -> np.ndarray:
    """``(n, 2)`` windowed positions of the stars SEP finds in one frame."""
    data = image.astype(np.float64)
    background = sep.Background(data)
    data -= background.back()
    objects = sep.extract(data, 1.5, err=background.globalrms)
    if len(objects) == 0:
        return np.zeros((0, 2))
    radius, _ = sep.flux_radius(data, objects["x"], objects["y"], 6.0 * objects["a"], 0.5, subpix=5)
    sigma = 2.0 / 2.35 * np.where(radius > 0, radius, 1.0)
    x, y, _ = sep.winpos(data, objects["x"], objects["y"], sigma)
    return np.column_stack([x, y])


def new_filter(position: np.ndarray, dt: float) -> UnscentedKalmanFilter:
    """A UKF of a static star at ``position``: state (x, y), identity motion, random-walk process noise."""
    points = MerweScaledSigmaPoints(n=2, alpha=1e-3, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=dt, fx=lambda x, dt: x, hx=lambda x: x, points=points)
    ukf.x = position.astype(float)
    ukf.P *= MEASUREMENT_SIGMA_PX ** 2
    ukf.R *= MEASUREMENT_SIGMA_PX ** 2
    ukf.Q = np.eye(2) * RANDOM_WALK_PX ** 2
    return ukf


def track(filters: list[UnscentedKalmanFilter], measured: np.ndarray, dt: float) -> None:
    """Predict every filter, update each with its nearest detection within the gate, start filters for the rest."""
    for ukf in filters:
        ukf.predict(dt=dt)
    used = np.zeros(len(measured), dtype=bool)
    if filters and len(measured):
        predicted = np.array([ukf.x for ukf in filters])
        distance = np.linalg.norm(predicted[:, None, :] - measured[None, :, :], axis=2)
        for k, ukf in enumerate(filters):
            j = int(np.argmin(distance[k]))
            if distance[k, j] < GATE_PX and not used[j]:
                ukf.update(measured[j])
                used[j] = True
    filters.extend(new_filter(z, dt) for z in measured[~used])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log")
    parser.add_argument("output")
    parser.add_argument("--topic", default="/camera/image")
    args = parser.parse_args(argv)
    filters: list[UnscentedKalmanFilter] = []
    times, positions = [], []
    last = None
    with open(args.log, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, message, image in reader.iter_decoded_messages(topics=[args.topic]):
            pixels = np.frombuffer(image.data, dtype=np.uint16).reshape(image.height, image.width)
            dt = 0.0 if last is None else (message.log_time - last) * 1e-9
            last = message.log_time
            track(filters, centroids(pixels), dt)
            times.append(message.log_time)
            positions.append(np.array([ukf.x for ukf in filters]))
    counts = np.array([len(p) for p in positions])
    np.savez(args.output, log_time=np.array(times), counts=counts,
             positions=np.concatenate(positions) if positions else np.zeros((0, 2)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
