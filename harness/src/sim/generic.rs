//! PLACEHOLDER, being replaced: answers every request with exception 04 so the tree builds.
use std::time::Duration;

use super::{DriveModel, FaultSet};
use crate::frame::{ExceptionCode, Request, Response};
use crate::profile::Profile;

/// Placeholder model.
pub struct Generic {
    profile: Profile,
}

impl Generic {
    /// Build the model from its profile.
    pub fn new(profile: Profile, _faults: FaultSet) -> Self {
        Self { profile }
    }
}

impl DriveModel for Generic {
    fn profile(&self) -> &Profile {
        &self.profile
    }
    fn advance(&mut self, _now: Duration) {}
    fn handle(&mut self, _now: Duration, _unit: u8, request: &Request) -> Option<Response> {
        Some(Response::exception(
            request.function(),
            ExceptionCode::SERVER_DEVICE_FAILURE,
        ))
    }
}
