//! The `[metrics]` section: where the metrics endpoint listens. Knows nothing of HTTP.

use super::defaults;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Metrics {
    pub listen: SocketAddr,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics {
            listen: defaults::metrics_listen(),
        }
    }
}
