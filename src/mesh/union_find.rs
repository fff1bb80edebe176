//! Union-find (disjoint sets) for connected components of meshes and surfaces.

/// Union-find with path halving and union by size.
pub(crate) struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
}

impl UnionFind {
    /// `n` singletons.
    pub(crate) fn new(n: usize) -> Self {
        Self {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
        }
    }

    /// Representative of `x`.
    pub(crate) fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = p;
        }
        x
    }

    /// Compact set labels (0, 1, ... in order of first appearance) for a sequence of elements,
    /// and the number of distinct sets seen.
    pub(crate) fn labels(&mut self, elements: impl Iterator<Item = u32>) -> (Vec<u32>, usize) {
        let mut id_of_root = vec![u32::MAX; self.parent.len()];
        let mut count = 0u32;
        let ids = elements
            .map(|e| {
                let r = self.find(e) as usize;
                if id_of_root[r] == u32::MAX {
                    id_of_root[r] = count;
                    count += 1;
                }
                id_of_root[r]
            })
            .collect();
        (ids, count as usize)
    }

    /// Merges the sets of `a` and `b`.
    pub(crate) fn union(&mut self, a: u32, b: u32) {
        let (mut ra, mut rb) = (self.find(a), self.find(b));
        if ra == rb {
            return;
        }
        if self.size[ra as usize] < self.size[rb as usize] {
            std::mem::swap(&mut ra, &mut rb);
        }
        self.parent[rb as usize] = ra;
        self.size[ra as usize] += self.size[rb as usize];
    }
}
