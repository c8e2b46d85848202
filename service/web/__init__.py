"""``azimuthd web``: a browser dashboard of every azimuthd on the Zenoh network (docs/DASHBOARD.md).

``hub`` keeps what Zenoh delivers (per vehicle: latest payload per topic, liveliness, the
dead-reckoned track) and fans it out to the browsers; ``server`` serves the page and its static
files from this package (no CDN, no internet) and the live stream as Server-Sent Events.
"""
