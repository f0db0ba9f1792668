"""Benchmarks and the plain NumPy engine; not part of the installed `snac_jax` package.

A regular package (not a namespace one) so that `import bench.numpy_engine` from the repository
root finds this directory even if some installed distribution also ships a `bench` module.
"""
