#![doc = include_str!("../README.md")]
#![warn(missing_docs)]

mod image;
pub mod interp;
mod microscope;

pub use image::{ChannelOptions, ImageError, ImageTiming, MIN_SIDE_PX, StoredImage};
pub use microscope::{
    MAX_SCAN_PIXELS, VirtualError, VirtualMicroscope, VirtualParams, VirtualSurface,
};
