//! `radserve policy-runtime` without the server: this crate's tests start it (radserve_policy::runtime).

fn main() -> std::process::ExitCode {
    radserve_policy::runtime::main_from_args(std::env::args().skip(1))
}
