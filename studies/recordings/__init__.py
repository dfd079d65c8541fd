"""Bring your recordings (issue 51): studies that run the project's readers and decoders on public real
recordings and compare what they produce with the output of other decoders on the same recordings.

- `reference`: velodyne-decoder (the project's Velodyne decoding) against nebula's ground-truth clouds
  of a VLP-16 and a VLP-32C recording (tests/fixtures/real/nebula_velodyne/), point by point; the table
  in docs/recordings.md.
"""
