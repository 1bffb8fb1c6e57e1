fn main() {
    std::process::exit(lightfuse::cli::main());
}
