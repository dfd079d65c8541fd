"""Process supervision beyond supervisord's restart-on-exit: stalled loops and crash loops (`watchdog`)."""
