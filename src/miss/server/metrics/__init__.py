"""What operators watch: the Prometheus registry and health checks (``registry``), and
the numbers every server process of a host shares through files (``files``)."""
