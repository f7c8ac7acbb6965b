//! `formation-layout`: prints the wire payloads' memory layout and the protocol's constants as
//! JSON (what bindings in other languages mirror), or with `--protocol-version` only the
//! protocol version (the launcher writes it into `run.json`).

fn main() -> std::process::ExitCode {
    match std::env::args().nth(1).as_deref() {
        None => print!("{}", formation_protocol::layout::layout_json()),
        Some("--protocol-version") => println!("{}", formation_protocol::wire::PROTOCOL_VERSION),
        Some("-h" | "--help") => {
            println!("Usage: formation-layout [--protocol-version]");
            println!("Prints the wire payloads' layout (size, alignment, iceoryx2 type name, field offsets)");
            println!("and the protocol's constants as JSON; --protocol-version prints only the version.");
        }
        Some(other) => {
            eprintln!("formation-layout: error: unknown argument '{other}' (try --help)");
            return std::process::ExitCode::from(2);
        }
    }
    std::process::ExitCode::SUCCESS
}
