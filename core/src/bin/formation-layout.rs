//! `formation-layout`: prints the wire payloads' memory layout, the protocol's constants and
//! every observation model's named offsets as JSON (what bindings in other languages read), or
//! with `--protocol-version` only the protocol version (the launcher writes it into `run.json`).

fn main() -> std::process::ExitCode {
    match std::env::args().nth(1).as_deref() {
        None => print!("{}", formation_core::layout::layout_json()),
        Some("--protocol-version") => println!("{}", formation_protocol::wire::PROTOCOL_VERSION),
        Some("-h" | "--help") => {
            println!("Usage: formation-layout [--protocol-version]");
            println!("Prints the wire payloads' layout (size, alignment, iceoryx2 type name, field offsets),");
            println!("the protocol's constants and the observation models (dimension, named blocks) as JSON;");
            println!("--protocol-version prints only the version.");
        }
        Some(other) => {
            eprintln!("formation-layout: error: unknown argument '{other}' (try --help)");
            return std::process::ExitCode::from(2);
        }
    }
    std::process::ExitCode::SUCCESS
}
