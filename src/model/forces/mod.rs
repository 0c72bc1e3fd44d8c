//! Applied forces (section V): data turned into point forces on the model's surface.

pub mod image;
pub mod range;
