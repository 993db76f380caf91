"""Pure numpy/scipy estimation core: filters, motion and measurement models, IMM.

Nothing in this package imports web, storage or I/O code; the service layers above it only
validate, route, store and serialise.
"""
