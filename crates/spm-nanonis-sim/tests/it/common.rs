//! What the backend tests share: a `NanonisConfig` for `nanonis-sim` on loopback — 16-bit DACs,
//! Z in signal 30, the controller's clock in signals 126/127, an upright frame scanned up, 5 s
//! per command, 2 reconnects. Each test changes what it is about with struct-update syntax.

use spm_nanonis::{ClockSource, NanonisConfig, SlowDirection};

/// The loopback configuration for a server on `port`.
pub fn loopback_config(port: u16) -> NanonisConfig {
    NanonisConfig {
        host: "127.0.0.1".into(),
        port,
        connect_timeout_s: 1.0,
        command_timeout_s: 5.0,
        wait_margin_s: 2.0,
        reconnect_attempts: 2,
        reconnect_backoff_s: 0.02,
        lateral_dac_bits: 16,
        z_dac_bits: 16,
        z_channel: 30,
        clock: ClockSource::ControllerSignals {
            whole_s_signal: 126,
            fraction_s_signal: 127,
        },
        max_pixels_per_line: 4096,
        max_lines: 4096,
        min_pixel_dwell_s: 1e-6,
        coarse_z: None,
        frame_angle_deg: 0.0,
        slow_direction: SlowDirection::Up,
    }
}
