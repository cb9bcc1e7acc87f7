"""Command-line tools that talk to the service or evaluate its models offline; not on the request path."""
