"""One module per resource: auth (and users), volumes, models, shares (and the ``/s/``
pages), rooms (the WebSocket and its replay), audit, and the HTML pages."""
