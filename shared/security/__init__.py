"""Identities and signatures: the local CA and service certificates (`pki`), signed route plans
(`plan_signing`), and the Zenoh TLS / access-control configuration generated from proto/streams.yaml."""
