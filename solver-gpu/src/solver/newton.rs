//! [`SpdSolver::power_sum_newton`] on the device: the scale factors'
//! estimation as batches of Newton steps ([`crate::power_sum_newton`]),
//! solved with the kind's own f64 factor, where the adapter has `SHADER_F64`.

use super::*;
use crate::power_sum_newton::{self as newton, NewtonData, NewtonKernels};
use solver_cpu::{NewtonInfo, NewtonRules, PowerSum};

impl GpuSolver {
    /// The estimation on the device, or `None` where it is left to the
    /// host's steps: another system kind, no f64 kernels or no f64 factor
    /// of the prepared matrix, a problem the kernels do not take
    /// ([`newton::unsupported`], a repeated unknown), or buffers past the
    /// device's limits.
    pub(super) fn newton_on_device(
        &mut self,
        constraints: &[PowerSum],
        rules: &NewtonRules,
        s: &mut [f64],
    ) -> Option<Result<NewtonInfo, GpuError>> {
        let n = self.host.as_ref()?.n();
        let factor = self.chol.as_ref()?;
        if self.kind != SystemKind::ScaleFactors
            || !self.ctx.shader_f64
            || factor.precision != precision::Precision::F64
            || self.chol_kind != Some(SystemKind::ScaleFactors)
            || s.len() != n
        {
            return None;
        }
        if let Some(why) = newton::unsupported(constraints, n) {
            log::debug!("scale factors' Newton steps on the host: {why}");
            return None;
        }
        let k = constraints.len();
        let entries: usize = constraints.iter().map(|c| c.coeffs.len()).sum();
        let stamp = self.setups;
        if self.newton_kernels.is_none() {
            match NewtonKernels::new(&self.ctx) {
                Ok(kern) => self.newton_kernels = Some(kern),
                Err(e) => return Some(Err(e)),
            }
        }
        let kernels = self.newton_kernels.as_ref()?;
        if !self
            .newton
            .as_ref()
            .is_some_and(|d| d.fits(n, k, entries, stamp))
        {
            // Room for a tenth more entries: a curve's faces may grow.
            let room = entries + entries / 10;
            let made = NewtonData::new(
                &self.ctx,
                kernels,
                self.chol_kernels.as_ref()?,
                factor,
                n,
                k,
                room.max(1),
                stamp,
                matrix::binding_limit(&self.ctx),
            );
            match made {
                Ok(mut d) => {
                    // The packing's vectors and the last estimation's steps carry over.
                    if let Some(old) = self.newton.take() {
                        d.packed = old.packed;
                        d.mark = old.mark;
                        d.last_steps = old.last_steps;
                    }
                    self.newton = Some(d);
                }
                Err(e @ GpuError::LimitExceeded { .. }) => {
                    log::debug!("scale factors' Newton steps on the host: {e}");
                    return None;
                }
                Err(e) => return Some(Err(e)),
            }
        }
        let data = self.newton.as_mut()?;
        if !data.packed.fill(constraints, n, &mut data.mark) {
            log::debug!(
                "scale factors' Newton steps on the host: an unknown out of range or repeated \
                 within a constraint"
            );
            return None;
        }
        let t = std::time::Instant::now();
        let waits = self.ctx.traffic().waits;
        let est = match newton::estimate(&self.ctx, kernels, data, rules, s) {
            Ok(e) => e,
            Err(e) => {
                self.newton = None;
                return Some(Err(e));
            }
        };
        for _ in 0..est.solves {
            self.work.solved(0);
        }
        log::debug!(
            "scale factors on the GPU: {} Newton steps (stop {}), max |C| {:.2e}, {} batches, \
             {} host waits, {:.3} s",
            est.info.steps,
            est.done,
            est.info.max_residual,
            est.batches,
            self.ctx.traffic().waits - waits,
            t.elapsed().as_secs_f64()
        );
        Some(Ok(est.info))
    }
}
