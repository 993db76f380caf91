"""Shared constants of the load generator tests."""

ADMIN_KEY = "loadgen-test-admin-key-0123456789"
