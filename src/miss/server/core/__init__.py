"""The server's HTTP plumbing: settings, errors, typed dependencies, authentication,
security headers, rate limits, log masking, the web assets, request schemas and the
``next`` path after login."""
