//! `TRANSFORM`: an affine transform, the upper 3×4 of its matrix as 12 big-endian `float32`,
//! column by column. This module owns [`Transform`] and its content encoding.

use crate::error::WireError;
use crate::reader::be_f32s;

/// Size of a `TRANSFORM` content: 12 `float32`.
pub const TRANSFORM_CONTENT_SIZE: usize = 48;

/// `TRANSFORM`: an affine transform; translation in millimetres.
///
/// On the wire the upper 3×4 of the matrix, column by column (R11 R21 R31 R12 ... TX TY TZ), as
/// `float32`; the bottom row is implied `[0, 0, 0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Row-major homogeneous matrix: `matrix[row][column]`, translation in `matrix[0..3][3]`
    /// (mm). Encoding rounds to `float32` and requires the bottom row `[0, 0, 0, 1]`.
    pub matrix: [[f64; 4]; 4],
}

impl Transform {
    /// The identity transform.
    pub const IDENTITY: Transform = Transform {
        matrix: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };

    /// The 12 wire values, column-major over the upper 3×4.
    pub fn to_wire(&self) -> Result<[f32; 12], WireError> {
        let bottom = self.matrix[3];
        if bottom != [0.0, 0.0, 0.0, 1.0] {
            return Err(WireError::Value {
                section: "TRANSFORM",
                field: "matrix row 4".into(),
                problem: format!(
                    "is {bottom:?}; TRANSFORM carries only the upper 3x4, the bottom row must be \
                     [0, 0, 0, 1]"
                ),
            });
        }
        let mut wire = [0f32; 12];
        for (column, values) in wire.chunks_exact_mut(3).enumerate() {
            for (row, value) in values.iter_mut().enumerate() {
                *value = self.matrix[row][column] as f32;
            }
        }
        Ok(wire)
    }

    /// From the 12 wire values, column-major over the upper 3×4.
    pub fn from_wire(wire: &[f32; 12]) -> Transform {
        let mut matrix = Transform::IDENTITY.matrix;
        for (column, values) in wire.chunks_exact(3).enumerate() {
            for (row, &value) in values.iter().enumerate() {
                matrix[row][column] = f64::from(value);
            }
        }
        Transform { matrix }
    }

    pub(crate) fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        Ok(self
            .to_wire()?
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect())
    }

    pub(crate) fn decode_content(content: &[u8]) -> Result<Transform, WireError> {
        if content.len() != TRANSFORM_CONTENT_SIZE {
            return Err(WireError::Value {
                section: "TRANSFORM",
                field: "content".into(),
                problem: format!(
                    "is {} bytes, a TRANSFORM has exactly {TRANSFORM_CONTENT_SIZE} (12 float32)",
                    content.len()
                ),
            });
        }
        let mut wire = [0f32; 12];
        for (w, v) in wire.iter_mut().zip(be_f32s(content)) {
            *w = v;
        }
        Ok(Transform::from_wire(&wire))
    }
}
