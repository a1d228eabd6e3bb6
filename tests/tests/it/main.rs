//! The integration tests of `spmcal-tests`, one binary (docs/ARCHITECTURE.md, "Tests"): a
//! module per topic, run as `cargo test -p spmcal-tests --test it <module>::`.

mod common;

mod calibration_end_to_end;
mod correction_end_to_end;
mod images_end_to_end;
mod nanonis_end_to_end;
mod nanonis_frame_angle;
mod nanonis_smoke;
mod report_html;
mod repository;
mod vertical_end_to_end;
