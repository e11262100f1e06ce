"""The live web view of a running mocapd (`mocapd start --view HOST:PORT`).

Two halves: `daemon.view.link` runs inside the daemon (a per-frame hook that only keeps
the newest result, and a feeder thread that packs it and hands it to the view process),
`daemon.view.app` is the view process (a viser server: thumbnails, per-camera figures,
the 3D scene, bodies made from picked markers). The view talks back to the daemon only
through its control socket, as `mocapd status` and `mocapd rigid-body add` do.
"""
