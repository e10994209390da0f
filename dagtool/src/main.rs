//! `dagtool`: convert meshes to `.vdag`, validate, inspect and verify.

fn main() {
    eprintln!("dagtool: not implemented yet");
    std::process::exit(2);
}
