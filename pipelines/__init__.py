"""Scheduled and demonstration jobs built on ident's public API (see README.md here)."""
