"""Flows for tests/test_starved.py: a camera whose step returns its frame under a misspelled key
(from a variable, so nothing can read the key before the run), a policy and a controller. Module
level, so that the zenoh workers can rebuild them from the IR."""

from __future__ import annotations

from retriever import Flow, Latest, Pipeline, Rate


class MisspeltCamera(Flow):
    def step(self):
        out = {"imgae": 1.0}
        return out


class InterruptedCamera(MisspeltCamera):
    """Ctrl-C, as its 21st step: a run interrupted at a tick a test can name."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        if self.k == 21:
            raise KeyboardInterrupt
        return super().step()


class Camera(Flow):
    def step(self):
        return {"image": 1.0}


class Policy(Flow):
    def step(self, image):
        return {"chunk": image}


class Controller(Flow):
    def step(self, chunk):
        return None


def camera_policy_controller(camera: Flow) -> Pipeline:
    with Pipeline("agent", deadline=1.0) as pipe:
        cam = camera.configure(name="cam") @ Rate(hz=10)
        pol = Policy().configure(name="policy") @ Rate(hz=5)
        ctrl = Controller().configure(name="controller") @ Rate(hz=20)
        cam.then(pol).then(ctrl)
    return pipe


class Viewer(Flow):
    def step(self, image):
        return None


def stale_viewer(staleness: float) -> Pipeline:
    """A viewer that takes only frames younger than ``staleness``: at the camera's rate, in real
    time, the newest frame at each of its ticks is one period old, so with less than that it
    never gets one, while the camera makes a frame every tick."""
    with Pipeline("stale") as pipe:
        cam = Camera().configure(name="cam") @ Rate(hz=20)
        viewer = Viewer().configure(name="viewer") @ Rate(hz=20)
        cam.then(viewer, sync=Latest(staleness=staleness))
    return pipe
