//! Kernel time of one compute pass from GPU timestamp queries (when the adapter has them),
//! so that benchmarks separate kernel time from upload and readback.

use std::time::Duration;

use super::GpuContext;
use crate::Result;

/// Two timestamps around one compute pass, resolved and read back for the kernel time.
#[derive(Debug)]
pub struct PassTimer {
    queries: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    staging: wgpu::Buffer,
}

impl PassTimer {
    /// Timer of the kernel `name` (used in the buffer labels).
    pub fn new(ctx: &GpuContext, name: &str) -> Self {
        let device = ctx.device();
        let bytes = 2 * u64::from(wgpu::QUERY_SIZE);
        Self {
            queries: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some(&format!("{name} timer")),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(&format!("{name} timer resolve")),
                size: bytes,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            staging: ctx.staging_buffer(&format!("{name} timer readback"), bytes),
        }
    }

    /// The pass descriptor's timestamp writes.
    pub fn writes(&self) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.queries,
            beginning_of_pass_write_index: Some(0),
            end_of_pass_write_index: Some(1),
        }
    }

    /// Records the resolve and the copy to the readback buffer after the pass.
    pub fn record_resolve(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.resolve_query_set(&self.queries, 0..2, &self.resolve, 0);
        encoder.copy_buffer_to_buffer(&self.resolve, 0, &self.staging, 0, self.resolve.size());
    }

    /// Elapsed GPU time between the two timestamps (submitted work must include the resolve).
    pub fn read(&self, ctx: &GpuContext) -> Result<Duration> {
        let ticks = ctx.read_mapped(&self.staging, |raw| {
            let t: &[u64] = bytemuck::cast_slice(&raw[..16]);
            t[1].saturating_sub(t[0])
        })?;
        let ns = ticks as f64 * f64::from(ctx.queue().get_timestamp_period());
        Ok(Duration::from_nanos(ns.round() as u64))
    }
}
