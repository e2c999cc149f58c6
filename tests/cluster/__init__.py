"""The container and cluster tests (make test-cluster): a package, so that pytest puts tests/ on
sys.path for them as for the other tests, and they import its helpers (k8s_harness) by name."""
