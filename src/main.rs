use clap::Parser;

fn main() {
    let cli = skillaug::cli::Cli::parse();
    if let Err(e) = skillaug::run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
