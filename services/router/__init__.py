"""Local Zenoh router: a router-mode session every other service connects to as a client."""
