"""``--clock wall``: the simulated camera in a process of its own (pybullet holds the GIL while it
renders, so it must not share a process with the control loop or the physics).

It renders each ``RenderRequest`` from the world process — the scene as it was at the frame's
capture instant — applies the sensor model, waits until the frame's delivery time (capture +
latency ± jitter, as a real OAK delivers 100–130 ms late) and sends the ``Frame`` to its
consumer. When rendering falls behind the frame rate it renders only the newest request: the
frames in between are dropped, as a real camera's newest-only queue would drop them.
"""

from __future__ import annotations

import contextlib
import os
import time
from multiprocessing.connection import Connection

import numpy as np

from configuration.camera import CameraConfig
from configuration.mockup import MockupConfig
from configuration.render import NoiseConfig, RenderConfig
from configuration.vision import CameraTiming
from sim_backends.camera import SimCamera, Viewpoint
from sim_backends.renderer import make_renderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import NoisePool
from sim_backends.world_server import CAMERA_NICE, LatestSender, RenderRequest


def camera_main(
    mockup: MockupConfig,
    camera: CameraConfig,
    noise: NoiseConfig,
    render: RenderConfig,
    timing: CameraTiming,
    seed: int,
    requests: Connection,
    frames: Connection,
    ready: Connection,
) -> None:
    """The camera process: render requests in, frames out (each at its delivery time).

    It renders ahead of the estimators when the system allows (``CAMERA_NICE``): a real
    camera's frames come on time however busy the host is, and a simulated one that waited
    for the estimators' cores would hand them frames later than any rig would."""
    with contextlib.suppress(OSError):  # not allowed to raise its priority: it runs as it is
        os.nice(CAMERA_NICE)
    with contextlib.suppress(KeyboardInterrupt), MockupScene(mockup) as scene:
        view: list[Viewpoint] = []  # each request's
        sim_camera = SimCamera(
            make_renderer(scene, camera.camera_info(), render),
            lambda: view[-1],
            noise,
            seed=seed,
            noise_draws=NoisePool(seed),  # its frames depend on the timing anyway
        )
        sim_camera.connect()
        sim_camera.activate()
        rng = np.random.default_rng([seed, 0x1A7E])
        outgoing = LatestSender(frames)  # a reader that fell behind gets the newest frame
        ready.send("ready")
        while True:
            try:
                request = requests.recv()
                while request is not None and requests.poll(0):  # newest only
                    request = requests.recv()
            except (EOFError, OSError):
                return
            if request is None:
                return
            assert isinstance(request, RenderRequest)
            scene.set_pose(request.X_WT)
            view[:] = [request.view]
            frame = sim_camera.render_frame(stamp=request.stamp, seq=request.seq)
            jitter = rng.uniform(-timing.jitter_s, timing.jitter_s) if timing.jitter_s else 0.0
            delay = request.stamp + timing.latency_s + jitter - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if outgoing.broken:
                return
            outgoing.put(frame)  # the receiver stamps its arrival
            outgoing.wait_sent(timeout_s=1.0 / timing.fps)
