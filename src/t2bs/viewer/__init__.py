"""Web viewer (viser): `t2bs view DIR`. Importing this package does not import viser."""
