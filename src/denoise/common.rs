//! Pieces the mesh and point operators share: why a point stayed put ([`stay`]), merging a
//! pass's results ([`merge_step`]), the faces around each vertex ([`FaceTopology`]) and the mean
//! edge length of a mesh ([`mean_edge_length`]). `qem`, `filtered`, `bilateral`, `guarded` and
//! `cloud` use them; nothing here uses those files.

use glam::DVec3;
use rayon::prelude::*;

use crate::geometry::ExactSum;
use crate::neighbours::MeshAdjacency;
use crate::points::Faces;

/// Why a point stayed where it was in a pass (bit flags, or-ed over passes).
pub mod stay {
    /// The summed quadric was singular, or the solve not finite.
    pub const SINGULAR: u8 = 1;
    /// The minimiser lay farther than the point's neighbourhood reaches (isolated points and
    /// outliers, whose planes all belong to a distant surface).
    pub const FAR: u8 = 2;
    /// The guarded step's total displacement was clamped to the bound of the local noise (or to
    /// `--max-move`).
    pub const BOUNDED: u8 = 4;
    /// Fewer than k points lie within the isolation radius: the point keeps its input position
    /// ([`crate::denoise::isolation`]).
    pub const ISOLATED: u8 = 8;
    /// Not of a class `--classes` names: the point keeps its input position and still serves as
    /// a neighbour.
    pub const HELD: u8 = 16;
}

/// Splits a pass's results into positions, or-ing its [`stay`] flags into `stayed`.
pub fn merge_step(step: Vec<(DVec3, u8)>, stayed: &mut [u8]) -> Vec<DVec3> {
    step.into_iter()
        .zip(stayed.iter_mut())
        .map(|((p, s), acc)| {
            *acc |= s;
            p
        })
        .collect()
}

/// Faces around each vertex and faces sharing a vertex with each face, in CSR form.
#[derive(Debug, Clone)]
pub struct FaceTopology {
    vertex_offsets: Vec<u32>,
    vertex_faces: Vec<u32>,
    face_offsets: Vec<u32>,
    face_neighbours: Vec<u32>,
}

impl FaceTopology {
    /// Builds the topology of `faces` over `n` vertices (indices already validated).
    pub fn build(n: usize, faces: &Faces) -> FaceTopology {
        let mut count = vec![0u32; n + 1];
        for f in faces.iter() {
            for &v in f {
                count[v as usize + 1] += 1;
            }
        }
        for v in 0..n {
            count[v + 1] += count[v];
        }
        let vertex_offsets = count.clone();
        let mut fill = count;
        let mut vertex_faces = vec![0u32; vertex_offsets[n] as usize];
        for (fi, f) in faces.iter().enumerate() {
            for &v in f {
                vertex_faces[fill[v as usize] as usize] = fi as u32;
                fill[v as usize] += 1;
            }
        }
        let lists: Vec<Vec<u32>> = (0..faces.len())
            .into_par_iter()
            .map(|fi| {
                let mut l: Vec<u32> = faces
                    .face(fi)
                    .iter()
                    .flat_map(|&v| {
                        let v = v as usize;
                        vertex_faces[vertex_offsets[v] as usize..vertex_offsets[v + 1] as usize]
                            .iter()
                            .copied()
                    })
                    .collect();
                l.sort_unstable();
                l.dedup();
                l
            })
            .collect();
        let mut face_offsets = Vec::with_capacity(faces.len() + 1);
        face_offsets.push(0u32);
        let mut face_neighbours = Vec::new();
        for l in lists {
            face_neighbours.extend_from_slice(&l);
            face_offsets.push(face_neighbours.len() as u32);
        }
        FaceTopology {
            vertex_offsets,
            vertex_faces,
            face_offsets,
            face_neighbours,
        }
    }

    /// The faces around vertex `v`, ascending.
    #[inline]
    pub fn faces_of(&self, v: usize) -> &[u32] {
        &self.vertex_faces[self.vertex_offsets[v] as usize..self.vertex_offsets[v + 1] as usize]
    }

    /// The faces sharing a vertex with face `f` (itself included), ascending.
    #[inline]
    pub fn neighbours_of(&self, f: usize) -> &[u32] {
        &self.face_neighbours[self.face_offsets[f] as usize..self.face_offsets[f + 1] as usize]
    }
}

/// Mean length of the unique undirected edges, summed exactly.
pub fn mean_edge_length(pos: &[DVec3], adjacency: &MeshAdjacency) -> f64 {
    adjacency
        .edges()
        .map(|(a, b)| (pos[a as usize] - pos[b as usize]).length())
        .collect::<ExactSum>()
        .mean()
}
