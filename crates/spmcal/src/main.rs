//! The spmcal command-line program (placeholder until the calibration issue).
fn main() {
    eprintln!("spmcal: not implemented yet");
    std::process::exit(2);
}
