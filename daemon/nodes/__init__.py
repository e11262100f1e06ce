"""Capture nodes on other machines: blobs and clocks over Zenoh (docs/nodes.md)."""
