"""Process supervision beyond supervisord's restart-on-exit: stalled loops and crash loops (`watchdog`),
and the verdict on the closed loop from every service's health (`verdict`: `rmmdet health`, the viewer)."""
