"""``racecav viz``: a live Foxglove view of the bus (Foxglove SDK WebSocket server; extra ``viz``)."""
