"""Flows for tests/backends/zenoh/test_payloads.py and others (module level: workers rebuild them from the IR)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retriever import Burst, Flow, io


@io
@dataclass
class Frame:
    image: np.ndarray
    k: int


@io
@dataclass
class Seen:
    k: int
    checksum: int


def frame(k: int, size: int) -> np.ndarray:
    """Frame k: content that differs in every byte position and from frame to frame."""
    return ((np.arange(size, dtype=np.uint32) * 2654435761 + k) >> 7).astype(np.uint8)


class Camera(Flow[None, Frame]):
    """Frames of ``size`` bytes, reshaped to rows of 1 KiB, one per tick."""

    def __init__(self, size: int):
        self.size = size
        self.k = 0

    def step(self, inp: None) -> Frame:
        self.k += 1
        return Frame(image=frame(self.k, self.size).reshape(-1, 1024), k=self.k)


class BurstCamera(Flow):
    """Untyped: at tick k a burst of k frames of ``size`` bytes on ``image`` (frame numbers go on
    from burst to burst) and one of k small ints on ``k``."""

    def __init__(self, size: int):
        self.size, self.k, self.n = size, 0, 0

    def step(self):
        self.k += 1
        first, self.n = self.n, self.n + self.k
        return {"image": Burst(frame(i, self.size) for i in range(first, self.n)), "k": Burst(range(first, self.n))}


class Sums(Flow):
    """Checksums of the frames a Queue gave it, in order."""

    def step(self, image):
        return {"sums": [int(i.sum(dtype=np.uint64)) for i in image]}


class Viewer(Flow[Frame, Seen]):
    """What it got: frame k and a checksum of its bytes."""

    def step(self, inp: Frame) -> Seen:
        return Seen(k=inp.k, checksum=int(inp.image.sum(dtype=np.uint64)))


@io
@dataclass
class Mapped:
    zenoh_shm: int


def zenoh_segments() -> dict[str, int]:
    """The Zenoh shared-memory segments (``/dev/shm/*.zenoh``) mapped into this process: the bytes
    mapped of each, by path."""
    sizes: dict[str, int] = {}
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split()
            if len(fields) >= 6 and fields[5].startswith("/dev/shm/") and fields[5].endswith(".zenoh"):
                start, end = (int(x, 16) for x in fields[0].split("-"))
                sizes[fields[5]] = sizes.get(fields[5], 0) + end - start
    return sizes


def biggest_zenoh_segment() -> int:
    """The size of the biggest Zenoh shared-memory segment mapped into this process: its
    session's pool, once Zenoh has created it, or a pool it received from; 0 when there is none."""
    return max(zenoh_segments().values(), default=0)


class ShmWatcher(Flow[None, Mapped]):
    """The biggest Zenoh segment mapped into its own process when it steps."""

    def step(self, inp: None) -> Mapped:
        return Mapped(zenoh_shm=biggest_zenoh_segment())


@io
@dataclass
class ImageMapped:
    image: np.ndarray
    zenoh_shm: int


class ImageShmWatcher(Flow[None, ImageMapped]):
    """ShmWatcher beside a small image, on a port of array type (connect it: a node that may send
    big values)."""

    def step(self, inp: None) -> ImageMapped:
        return ImageMapped(image=np.zeros((2, 8), dtype=np.uint8), zenoh_shm=biggest_zenoh_segment())


class ShmOfImageTaker(Flow):
    """Untyped: takes an image; the biggest Zenoh segment of its own process."""

    def step(self, image):
        return {"zenoh_shm": biggest_zenoh_segment()}


class ShmOfScalarTaker(Flow[Mapped, Mapped]):
    """Takes an int only; the biggest Zenoh segment of its own process."""

    def step(self, inp: Mapped) -> Mapped:
        return Mapped(zenoh_shm=biggest_zenoh_segment())


class SegmentsTaker(Flow):
    """Untyped: takes an image; the Zenoh segments its own process maps, as [path, bytes] pairs."""

    def step(self, image):
        return {"segments": sorted(zenoh_segments().items())}


class Holder(Flow[None, dict]):
    """Emits what its constructor got, with the type of each part: how a worker rebuilt it."""

    def __init__(self, value):
        self.value = value

    def step(self, inp: None) -> dict:
        return {"types": [type(v).__name__ for v in self.value], "value": self.value}
