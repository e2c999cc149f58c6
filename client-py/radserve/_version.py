# The release of this package. radserve has one version, the Cargo workspace's
# (`[workspace.package] version` in Cargo.toml), which the server reports; tests/test_release.py fails
# when this line says anything else.
__version__ = "0.2.0"
