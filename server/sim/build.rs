// The worker embeds CPython: link libpython with an rpath so that the interpreter this project was
// built against is loaded, not another libpython that happens to be on the loader's path.
fn main() {
    pyo3_build_config::add_libpython_rpath_link_args();
}
