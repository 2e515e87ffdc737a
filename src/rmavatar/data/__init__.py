"""Datasets: PeopleSnapshot (InstantAvatar layout), ZJU-MoCap (monocular) and rmavatar's native format,
all read into the same `Frame` records (see docs/data.md)."""

from rmavatar.data.dataset import Dataset, FrameRecord
from rmavatar.data.frame import Frame
from rmavatar.data.native import NativeMeta, export_native, write_native
from rmavatar.data.registry import load_dataset
from rmavatar.render.camera import Camera

__all__ = ["Camera", "Frame", "Dataset", "FrameRecord", "load_dataset", "NativeMeta", "write_native", "export_native"]
