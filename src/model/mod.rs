//! The paper's model as pure functions and plain data (no ECS types): sections III–V and the
//! appendices of Terzopoulos & Metaxas, *Dynamic 3D Models with Local and Global Deformations:
//! Deformable Superquadrics*, IEEE PAMI 13(7), 1991.
//!
//! Read top to bottom: [`superquadric`] (s, J) → [`frame`] (R, B) → [`fem`] (tessellation,
//! element stiffness, K q) → [`dynamics`] (f_q, C, the Euler step) → [`forces`] (range springs, image
//! potentials) → [`init`] (moments) → [`fit`] (the loop to equilibrium for range data) →
//! [`parts`] (several parts on one cloud) → [`noise`] (the noise of a cloud and the stiffness it calls for) → [`image_fit`] (parts fitted to an image) → [`descriptor`] (fitted parts compared by their
//! global parameters).

pub mod centreline;
pub mod deform;
pub mod descriptor;
pub mod distance;
pub mod dynamics;
pub mod fem;
pub mod fit;
pub mod forces;
pub mod frame;
pub mod image_fit;
pub mod image_measure;
pub mod inertia;
pub mod init;
pub mod joint;
pub mod linalg;
pub mod lm;
pub mod nearest;
pub mod noise;
mod parallel;
pub mod parts;
mod simd;
pub mod superquadric;
pub mod track;
