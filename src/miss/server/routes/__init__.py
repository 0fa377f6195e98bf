"""One module per resource: volumes, models, and the HTML pages."""
