//! What several modules share.

use spm_nanonis_sim::server::ServerHandle;
use spm_nanonis_sim::{Server, ServerConfig, SocketFaults};
use spm_sim::SimConfig;

/// nanonis-sim on an ideal simulator, no socket faults, on a free loopback port.
#[allow(clippy::unwrap_used)]
pub fn serve_ideal() -> ServerHandle {
    Server::bind(
        "127.0.0.1:0",
        SimConfig::ideal(),
        ServerConfig::new(SocketFaults::none()),
    )
    .unwrap()
    .spawn()
    .unwrap()
}
