"""rmavatar: animatable human avatars from monocular video with rectified mesh-embedded Gaussians."""

__version__ = "0.1.0"
