"""Interactive browser viewer for avatars (viser), and headless-Chromium screenshots to test it."""
