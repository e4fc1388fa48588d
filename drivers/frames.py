"""What every frame source yields and counts: :class:`Frame`, :class:`CaptureStats`, and the
:class:`FrameSource` interface the pipeline consumes."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One captured image.

    Attributes
    ----------
    index : int
        0-based position in capture order. A frame that was dropped or could not be decoded
        still consumes its index, so gaps in ``index`` show losses.
    t : float
        Seconds. Video files: the frame's presentation timestamp (PTS) from the start of the
        file. Stills: EXIF DateTimeOriginal as seconds since the Unix epoch, or
        ``index / rate`` when the stills carry no EXIF time. Live cameras: the host's
        monotonic clock (``time.monotonic()``) when the frame was received.
    image : numpy.ndarray
        uint8, ``HxW`` (gray) or ``HxWx3`` (BGR, OpenCV order); deeper (16-bit, float) where a
        source delivers raw values (a Y16 camera). Stills folders stretch theirs to uint8 with
        one :class:`~photomap.core.stretch.RunningStretch` per flight; the mapping pipeline
        does the same with any deep frame that reaches it.
    source : str
        Where the frame came from: the still's file name, the video's file name, the device.
    """

    index: int
    t: float
    image: np.ndarray
    source: str


@dataclass
class CaptureStats:
    """Counters of a frame source (updated by the source while it runs).

    Attributes
    ----------
    read : int
        Frames obtained from the input (for a live camera, including those dropped later).
    dropped : int
        Frames discarded because the consumer fell behind (live sources only).
    corrupt : int
        Frames or files skipped because they could not be decoded.
    reconnects : int
        Recoveries of a live camera after it was lost (frames arrive again).
    """

    read: int = 0
    dropped: int = 0
    corrupt: int = 0
    reconnects: int = 0


@runtime_checkable
class FrameSource(Protocol):
    """What the pipeline consumes: iterate for frames, ``close()`` when done.

    Iteration ends at the end of the input or after ``close()``. ``live`` is true for sources
    whose frames arrive in real time (and may be dropped); false for replay.
    """

    stats: CaptureStats
    live: bool

    def __iter__(self) -> Iterator[Frame]: ...

    def close(self) -> None: ...


class SourceBase(ABC):
    """Context-manager support shared by the concrete sources."""

    stats: CaptureStats
    live: bool = False

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
