"""Pose fits pose a copy of the avatar without the Gaussians too faint to draw (``drawable_copy``): it must
render the same images and send the same gradients to the mesh as the whole avatar."""

import numpy as np
import pytest
import torch
from test_density import adam_with_state, make

from rmavatar.avatar import GAUSSIAN_PARAMS
from rmavatar.avatar.frame import render_frame
from rmavatar.avatar.model import drawable_copy
from rmavatar.render import Camera
from rmavatar.train.density import use_capacity

from devices import DEVICES

SIZE = 40


def _avatar(gen):
    """An icosphere avatar, two to three Gaussians per face, spread over their triangles, with a
    rectifier that moves them; a third of the Gaussians (every one of some faces) below 1/255."""
    av, v = make(n=200, rectifier="paper")
    with torch.no_grad():
        av.means.normal_(0.0, 0.3, generator=gen)
        av.log_scales.add_(-1.0 + 0.3 * torch.randn(av.log_scales.shape, generator=gen))
        av.quats.add_(0.3 * torch.randn(av.quats.shape, generator=gen))
        av.sh_dc.normal_(0.0, 1.0, generator=gen)
        av.opacity_logits.normal_(0.0, 1.0, generator=gen)
        faint = torch.rand(av.num_gaussians, generator=gen) < 0.3
        faint |= av.face_ids < 8  # whole faces: they leave the copy's binding faces
        av.opacity_logits[faint] = float(torch.logit(torch.tensor(0.99 / 255)))  # just below 1/255
        # and a fifth of the others just above it: they must be kept, each adds a little to the image
        faint_kept = ~faint & (torch.rand(av.num_gaussians, generator=gen) < 0.25)
        av.opacity_logits[faint_kept] = float(torch.logit(torch.tensor(1.01 / 255)))
        av.rectifier.l5.weight.normal_(0, 0.05, generator=gen)
    av.eval()
    return av, v + 0.02 * torch.randn(v.shape, generator=gen)


def _camera():
    K = np.array([[60.0, 0, SIZE / 2], [0, 60.0, SIZE / 2], [0, 0, 1]])
    viewmat = np.eye(4)
    viewmat[2, 3] = 2.5
    return Camera(K, viewmat, SIZE, SIZE)


def _render(av, vertices, pose, device):
    """The image, alpha and the gradient of a weighted image sum with respect to the mesh."""
    v = vertices.to(device).requires_grad_(True)
    drawn = render_frame(av, v, pose.to(device), _camera(), torch.ones(3, device=device))
    weights = torch.linspace(0.0, 1.0, drawn.image.numel(), device=device).reshape(drawn.image.shape)
    (drawn.image * weights).sum().backward()
    return drawn.image.detach(), drawn.alpha.detach(), v.grad


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("capacity", [False, True])
def test_the_drawable_copy_renders_and_differentiates_as_the_whole_avatar(device, capacity):
    gen = torch.Generator().manual_seed(5)
    av, vertices = _avatar(gen)
    if capacity:  # live rows first, then unused rows the copy must leave out too
        use_capacity(av, adam_with_state(av), 512)
    av = av.to(device)
    pose = 0.2 * torch.randn(69, generator=gen)
    for p in av.parameters():
        p.requires_grad_(False)
    before = {name: getattr(av, name).clone() for name in GAUSSIAN_PARAMS}
    slot = av.face_slot().clone()

    copy = drawable_copy(av)

    n = av.num_gaussians
    drawable = torch.sigmoid(av.opacity_logits[:n]) >= 1 / 255
    assert 0.2 * n < int((~drawable).sum()) < 0.6 * n
    assert copy.num_gaussians == copy.capacity == int(drawable.sum()) and copy.live is None
    assert torch.equal(copy.face_ids, av.face_ids[:n][drawable])
    assert torch.equal(copy.binding_faces, torch.unique(av.face_ids[:n][drawable]))
    assert copy.binding_faces.shape[0] < av.binding_faces.shape[0]  # whole faces left out
    image, alpha, grad = _render(av, vertices, pose, device)
    assert float(alpha.amax()) > 0.5 and float((alpha > 0.1).float().mean()) > 0.2  # the sphere is drawn
    image_c, alpha_c, grad_c = _render(copy, vertices, pose, device)
    torch.testing.assert_close(image_c, image, rtol=0, atol=1e-6)
    torch.testing.assert_close(alpha_c, alpha, rtol=0, atol=1e-6)
    assert float(grad.abs().amax()) > 0
    torch.testing.assert_close(grad_c, grad, rtol=1e-4, atol=1e-5 * float(grad.abs().amax()))
    # the avatar itself is untouched: its parameters, its rows' face slots
    for name, value in before.items():
        assert torch.equal(getattr(av, name), value), name
    assert torch.equal(av.face_slot(), slot)


def test_a_trained_avatar_is_loaded_without_its_faint_gaussians_and_draws_the_same(trained_run, tmp_path):
    """load_trained keeps only the drawable Gaussians (every_gaussian=True: all of them, as trained): a
    run whose checkpoint has a third of its Gaussians just below 1/255 poses fewer and renders the same
    frames; one with nothing to draw keeps them all."""
    import shutil

    from rmavatar.avatar import load_trained
    from rmavatar.avatar.run import read_checkpoint
    from rmavatar.body import PoseSequence
    from rmavatar.data import load_dataset
    from rmavatar.train.checkpoint import save_checkpoint

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    path = run / "checkpoints" / "last.pt"
    ckpt = read_checkpoint(path)
    logits = ckpt.avatar["state_dict"]["opacity_logits"]
    gen = torch.Generator().manual_seed(0)
    faint = torch.rand(logits.shape[0], generator=gen) < 0.3
    logits[faint] = float(torch.logit(torch.tensor(0.99 / 255)))
    save_checkpoint(path, ckpt)

    whole, drawn = load_trained(run, every_gaussian=True), load_trained(run)
    n = whole.avatar.num_gaussians
    assert n == logits.shape[0] and drawn.avatar.num_gaussians == n - int(faint.sum()) < 0.8 * n
    ds = load_dataset(whole.data_spec, size=whole.size)
    frame = ds.frame("train", 0)
    poses = PoseSequence.from_params(ds.params("train"))
    images = [t.render(t.pose(poses, 0), frame.camera) for t in (whole, drawn)]
    assert float((images[0] < 0.9).float().mean()) > 0.05  # the body is in the picture
    torch.testing.assert_close(images[1], images[0], rtol=0, atol=1e-6)
    assert drawable_copy(drawn.avatar) is drawn.avatar  # eval's pose fit does not copy it again

    logits.fill_(float(torch.logit(torch.tensor(0.5 / 255))))
    save_checkpoint(path, ckpt)
    assert load_trained(run).avatar.num_gaussians == n
