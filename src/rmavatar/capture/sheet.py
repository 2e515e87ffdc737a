"""The contact sheet of a capture: frames with the fitted body drawn over them, so a person sees at
once whether the fit is right."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rmavatar.capture.landmarks import BONES, USED

TILE_HEIGHT = 320
PER_ROW = 6
BODY_ALPHA = 0.5
BODY_COLOUR = np.array([1.0, 0.6, 0.15])  # orange: stands out on most clothes and skin


def body_silhouette(vertices_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int
                    ) -> np.ndarray:
    """Where the mesh (camera-frame vertices [V,3], faces [F,3]) covers a ``width`` x ``height`` image
    seen by K [3,3] (one sample per pixel, at its centre): [height,width] bool."""
    from rmavatar.data.synth.raster import rasterize

    return rasterize(vertices_cam, faces, K, width, height, ss=1).face_id >= 0


def body_overlay(image: np.ndarray, vertices_cam: np.ndarray, faces: np.ndarray, K: np.ndarray) -> np.ndarray:
    """image [H,W,3] float 0..1 with the mesh (camera-frame vertices [V,3], faces [F,3]) drawn over it,
    z-buffered, shaded by the angle to the viewer, half transparent. Returns [H,W,3] float."""
    from rmavatar.data.synth.raster import rasterize

    h, w = image.shape[:2]
    frags = rasterize(vertices_cam, faces, K, w, h, ss=1)
    tri = vertices_cam[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
    view = tri.mean(1)
    view /= np.linalg.norm(view, axis=1, keepdims=True) + 1e-12
    shade = 0.35 + 0.65 * np.abs((normal * view).sum(1))
    covered = frags.face_id >= 0
    colour = np.zeros((h, w, 3))
    colour[covered] = shade[frags.face_id[covered], None] * BODY_COLOUR
    a = covered[..., None] * BODY_ALPHA
    return image * (1 - a) + colour * a


def _draw_hands(draw, body_points: np.ndarray, landmarks: list[np.ndarray]) -> None:
    """The body's hand bones (points [2,21,2] in the tile, red) and MediaPipe's hand landmarks of the
    hands seen (each [21,2], green dots), thinner than the body's."""
    from rmavatar.capture.hands import POINT_PARENTS

    for hand in body_points:
        for a, b in enumerate(POINT_PARENTS[1:], start=1):
            draw.line([tuple(hand[a]), tuple(hand[b])], fill=(230, 30, 30), width=1)
    for points in landmarks:
        for u, v in points:
            draw.ellipse([u - 1, v - 1, u + 1, v + 1], fill=(20, 200, 60))


def contact_sheet(path: Path, body, camera, params: dict, splits: dict, clip, images: Path,
                  count: int = 12) -> list[dict]:
    """Write ``count`` frames spread over the clip: the fitted body over the frame, MediaPipe's
    landmarks (green dots) and the body's landmark points joined as a skeleton (red); with hand poses in
    ``params``, the hands' landmarks and bones alike, and which hands the frame saw in its label (L, R;
    "-" for a hand not seen, posed from the frames around it). ``images``: the
    dataset's images folder (frame i is ``{i:05d}.png``). Each tile is labelled with its split and the
    video's 0-based frame number (``clip.index``, capture.npz's ``source_index``); the same list is
    stored in the PNG as the text chunk ``frames`` (JSON) and returned: [{"frame": dataset frame,
    "video_frame": ..., "split": ...}]."""
    import json

    import torch
    from PIL import Image, ImageDraw, PngImagePlugin

    from rmavatar.capture.fit import project
    from rmavatar.capture.landmarks import body_landmarks, joint_rotations
    from rmavatar.data.io import read_image, resample

    n = len(clip.index)
    picks = sorted(set(np.linspace(0, n - 1, min(count, n)).round().astype(int).tolist()))
    split_of = {i: s for s, idx in splits.items() for i in idx}
    scale = min(1.0, TILE_HEIGHT / camera.height)
    tw, th = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    small = camera.resized(tw, th)
    K = small.K.astype(np.float64)
    dev = body.faces.device
    t = lambda key: torch.as_tensor(np.asarray(params[key])[picks], dtype=torch.float32, device=dev)  # noqa: E731
    betas = None
    if int(getattr(body, "num_betas", 0)):
        betas = torch.as_tensor(params["betas"][None, : min(10, body.num_betas)], device=dev).expand(len(picks), -1)
    with torch.no_grad():
        go, bp = t("global_orient"), t("body_pose")
        hands = "hand_pose" in params
        out = body(betas, go, bp, t("transl"), hand_pose=t("hand_pose") if hands else None)
        points = body_landmarks(out.joints, joint_rotations(go, bp))
        Kt = torch.as_tensor(K, dtype=torch.float32, device=dev)
        uv_body = project(points, Kt).cpu().numpy()
        uv_hands = project(out.hand_points, Kt).cpu().numpy() if hands and out.hand_points is not None else None
    vertices = out.vertices.cpu().numpy().astype(np.float64)
    faces = body.faces.cpu().numpy()
    rows = (len(picks) + PER_ROW - 1) // PER_ROW
    pad = 14
    sheet = Image.new("RGB", (PER_ROW * tw, rows * (th + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    pos = {k: i for i, k in enumerate(USED)}
    for slot, i in enumerate(picks):
        image = resample(read_image(images / f"{i:05d}.png"), tw, th)
        tile = body_overlay(image, vertices[slot], faces, K)
        x0, y0 = (slot % PER_ROW) * tw, (slot // PER_ROW) * (th + pad)
        sheet.paste(Image.fromarray((np.clip(tile, 0, 1) * 255 + 0.5).astype(np.uint8)), (x0, y0 + pad))
        off = np.array([x0, y0 + pad])
        for a, b in BONES:
            p, q = uv_body[slot, pos[a]] + off, uv_body[slot, pos[b]] + off
            draw.line([tuple(p), tuple(q)], fill=(230, 30, 30), width=2)
        for k in USED:
            u, v = clip.keypoints[i][k] * scale + off
            r = 2 if clip.visibility[i][k] > 0.5 else 1
            draw.ellipse([u - r, v - r, u + r, v + r], fill=(20, 200, 60))
        label = f"{split_of.get(i, '?')}, video frame {clip.index[i]}"
        if uv_hands is not None:
            seen = params["hand_found"][i]
            label += f", hands {'L' if seen[0] else '-'}{'R' if seen[1] else '-'}"
            _draw_hands(draw, uv_hands[slot].reshape(2, 21, 2) + off,
                        [clip.hands[i].keypoints[h] * scale + off for h in np.nonzero(seen)[0]])
        draw.text((x0 + 3, y0 + 1), label, fill=(0, 0, 0))
    labels = [{"frame": int(i), "video_frame": int(clip.index[i]), "split": split_of.get(i, "?")} for i in picks]
    info = PngImagePlugin.PngInfo()
    info.add_text("frames", json.dumps(labels))
    sheet.save(path, pnginfo=info)
    return labels
