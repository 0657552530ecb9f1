fn main() {
    std::process::exit(cncgw::cli::main());
}
