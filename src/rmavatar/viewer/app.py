"""An interactive browser viewer for an avatar, built on viser's Gaussian-splat renderer.

The page shows the avatar's Gaussians; with a motion there is a timeline slider, a play checkbox and
a playback speed; buttons put the camera in front of, beside or behind the body. viser draws splats
with one colour each, so view-dependent SH terms are dropped (the degree-0 colour is shown).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

# The Gaussians to show for a timeline frame: (means [N,3], quats [N,4], scales [N,3], opacities [N], sh [N,K,3]).
FrameFn = Callable[[int], tuple]

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic
CACHE_BYTES = 512 * 2**20  # memory for evaluated timeline frames (~1.6 MB a frame for 25k Gaussians)


def splat_arrays(means, quats, scales, opacities, sh) -> dict[str, np.ndarray]:
    """viser's splat inputs from world-space Gaussians.

    Returns centers [N,3], covariances [N,3,3] = R diag(s^2) R^T, rgbs [N,3] = clamp(C0 sh_0 + 0.5),
    opacities [N,1] (float32 numpy).
    """
    from rmavatar.render.project import quat_to_rotmat

    with torch.no_grad():
        R = quat_to_rotmat(torch.as_tensor(quats).float())
        M = R * torch.as_tensor(scales).float()[:, None, :]
        cov = M @ M.transpose(-1, -2)
        sh = torch.as_tensor(sh).float()
        rgb = (SH_C0 * sh[:, 0, :] + 0.5).clamp(0.0, 1.0)
        return {
            "centers": torch.as_tensor(means).float().cpu().numpy(),
            "covariances": cov.cpu().numpy(),
            "rgbs": rgb.cpu().numpy(),
            "opacities": torch.as_tensor(opacities).float().reshape(-1, 1).cpu().numpy(),
        }


@dataclass
class ViewerState:
    """What the viewer shows: frames of Gaussians, the playback rate and where the body stands."""

    frame_fn: FrameFn
    num_frames: int
    fps: float
    center: np.ndarray  # [3] the point the camera presets look at
    distance: float  # camera distance for the presets


class AvatarViewer:
    """A running viser server showing an avatar; ``close()`` stops it."""

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, verbose: bool = False):
        import viser

        self.state = state
        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.scene.set_up_direction("+y")
        self.server.gui.configure_theme(dark_mode=False, show_logo=False)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._shown = -1
        self._cache: dict[int, dict[str, np.ndarray]] = {}

        front = self._preset_pose("front")
        self.server.initial_camera.position = front[0]
        self.server.initial_camera.look_at = front[1]
        self.server.initial_camera.up = (0.0, 1.0, 0.0)
        self.server.initial_camera.fov = np.radians(40.0)

        self.splats = self.server.scene.add_gaussian_splats("/avatar", **splat_arrays(*state.frame_fn(0)))
        self._shown = 0

        with self.server.gui.add_folder("Camera"):
            for name in ("front", "side", "back"):
                button = self.server.gui.add_button(name.capitalize())
                button.on_click(lambda event, name=name: self.set_camera(name))
        self.frame_slider = None
        if state.num_frames > 1:
            with self.server.gui.add_folder("Motion"):
                self.frame_slider = self.server.gui.add_slider("Frame", 0, state.num_frames - 1, 1, 0)
                self.play = self.server.gui.add_checkbox("Play", False)
                top = float(max(60, round(state.fps)))  # mocap runs at up to 120-250 fps
                self.speed = self.server.gui.add_slider("FPS", 1.0, top, 1.0, float(min(max(round(state.fps), 1), top)))
            self.frame_slider.on_update(lambda _: self.show_frame(int(self.frame_slider.value)))
            self._player = threading.Thread(target=self._play_loop, daemon=True)
            self._player.start()

    @property
    def port(self) -> int:
        return self.server.get_port()

    def _preset_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        az = np.radians({"front": 0.0, "side": 90.0, "back": 180.0}[name])
        offset = np.array([np.sin(az), 0.0, np.cos(az)]) * self.state.distance
        return self.state.center + offset, self.state.center

    def set_camera(self, name: str) -> None:
        """Move every connected browser's camera to a preset: 'front', 'side' (the body's left) or 'back'."""
        position, look_at = self._preset_pose(name)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.up_direction = (0.0, 1.0, 0.0)
                client.camera.position = position
                client.camera.look_at = look_at

    def show_frame(self, index: int) -> None:
        """Replace the splats with the avatar at timeline frame ``index``."""
        with self._lock:
            if index == self._shown:
                return
            arrays = self._cache.get(index)
            if arrays is None:
                arrays = splat_arrays(*self.state.frame_fn(index))
                per_frame = sum(a.nbytes for a in arrays.values())
                # evaluating the avatar takes ~0.1 s a frame on a CPU: keep frames so loops replay smoothly
                if (len(self._cache) + 1) * per_frame <= CACHE_BYTES:
                    self._cache[index] = arrays
            self.splats.set_gaussians(**arrays)
            self._shown = index

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if self.play.value:
                start = time.monotonic()
                self.frame_slider.value = (int(self.frame_slider.value) + 1) % self.state.num_frames
                # the slider's update callback renders the frame; keep the chosen rate
                time.sleep(max(0.0, 1.0 / float(self.speed.value) - (time.monotonic() - start)))
            else:
                time.sleep(0.05)

    def close(self) -> None:
        self._stop.set()
        if self.frame_slider is not None:
            self._player.join(timeout=5.0)  # no frame update may race the server's shutdown
        self.server.stop()


def avatar_viewer(trained, seq=None, fps: float = 30.0, host: str = "127.0.0.1", port: int = 8080,
                  rest: str = "tpose", verbose: bool = False) -> AvatarViewer:
    """Start a viewer for ``trained`` (a :class:`rmavatar.avatar.TrainedAvatar`) playing the PoseSequence
    ``seq`` (re-centred like ``animate``), or standing in the rest pose ``rest`` when ``seq`` is None."""
    from rmavatar.animate.jobs import VideoOptions, frame_the_body
    from rmavatar.animate.motion import recenter_motion

    if seq is None:
        seq = trained.rest_pose(rest)
    else:
        seq = recenter_motion(seq, trained.root_rest())
    sample = seq.select(sorted({round(i * (len(seq) - 1) / 15) for i in range(min(len(seq), 16))}))
    # framed for a narrower view than the 40 degrees the browser gets: leaves room around the body
    center, distance = frame_the_body(trained.vertices(sample), VideoOptions(fov_deg=30.0))

    def frame_fn(i: int):
        gs = trained.pose(seq, i)
        return gs.means, gs.quats, gs.scales, gs.opacities, gs.sh

    state = ViewerState(frame_fn, len(seq), fps, center.cpu().numpy(), distance)  # numpy needs host memory
    return AvatarViewer(state, host=host, port=port, verbose=verbose)
