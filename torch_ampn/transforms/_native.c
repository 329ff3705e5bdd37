/* The "native" backend of the contact-edge search: a cell grid in plain C (CPU).
 *
 * For every node i and every other component c of its graph, the k nearest nodes j of
 * (graph, c) with |x_j - x_i|^2 <= r^2, nearest first, ties by the smaller index. Squared
 * distances are dx*dx + dy*dy + dz*dz in double, evaluated in that order with no fused
 * multiply-add (compiled with -ffp-contract=off), the same numbers as the PyTorch backends.
 *
 * Nodes are counting-sorted by (group, cell z, cell y, cell x), group = graph * C + component,
 * cells of edge h >= r (r, doubled while there would be more than max_cells), so the ball of radius r around a node lies in the 3 x 3 x 3 cells
 * around its cell; the three cells of one (z, y) row are consecutive in that order.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* Returns 0, or -1 when memory could not be allocated. */
int ampn_component_table(
    int64_t n,            /* nodes */
    const double *pos,    /* [n, 3] */
    const int64_t *group, /* [n] graph * C + component, in [0, num_groups) */
    int64_t num_components,
    int64_t num_groups,
    double r,
    int64_t max_cells,    /* cells of edge r unless more than this over all groups: then coarser */
    int64_t k,
    int64_t *nbr,         /* out [n, k * (C - 1)] */
    uint8_t *mask         /* out [n, k * (C - 1)] */
) {
    const int64_t C = num_components, width = k * (C - 1);
    const double r2 = r * r;
    if (n == 0) return 0;
    double lo[3] = {pos[0], pos[1], pos[2]}, hi[3] = {pos[0], pos[1], pos[2]};
    for (int64_t i = 1; i < n; ++i)
        for (int a = 0; a < 3; ++a) {
            double v = pos[3 * i + a];
            if (v < lo[a]) lo[a] = v;
            if (v > hi[a]) hi[a] = v;
        }
    int64_t dim[3];
    double h = r;
    for (;;) {
        double cells = (double)num_groups;
        for (int a = 0; a < 3; ++a) cells *= floor((hi[a] - lo[a]) / h) + 1.0;
        if (cells <= (double)max_cells) break;
        h *= 2.0;
    }
    for (int a = 0; a < 3; ++a) dim[a] = (int64_t)floor((hi[a] - lo[a]) / h) + 1;
    const int64_t per_group = dim[0] * dim[1] * dim[2];
    const int64_t num_cells = num_groups * per_group;
    int64_t *cell = malloc(sizeof(int64_t) * n);
    int64_t *start = calloc(num_cells + 1, sizeof(int64_t));
    int64_t *order = malloc(sizeof(int64_t) * n);
    int64_t *cx = malloc(sizeof(int64_t) * 3 * n);
    double *best_d = malloc(sizeof(double) * (k > 0 ? k : 1));
    int64_t *best_j = malloc(sizeof(int64_t) * (k > 0 ? k : 1));
    if (!cell || !start || !order || !cx || !best_d || !best_j) {
        free(cell); free(start); free(order); free(cx); free(best_d); free(best_j);
        return -1;
    }
    for (int64_t i = 0; i < n; ++i) {
        for (int a = 0; a < 3; ++a) {
            int64_t c = (int64_t)floor((pos[3 * i + a] - lo[a]) / h);
            if (c < 0) c = 0;
            if (c >= dim[a]) c = dim[a] - 1;
            cx[3 * i + a] = c;
        }
        cell[i] = group[i] * per_group + (cx[3 * i + 2] * dim[1] + cx[3 * i + 1]) * dim[0] + cx[3 * i];
        start[cell[i] + 1] += 1;
    }
    for (int64_t c = 0; c < num_cells; ++c) start[c + 1] += start[c];
    {   /* counting sort, stable: by cell, then by node index */
        int64_t *fill = malloc(sizeof(int64_t) * num_cells);
        if (!fill) {
            free(cell); free(start); free(order); free(cx); free(best_d); free(best_j);
            return -1;
        }
        for (int64_t c = 0; c < num_cells; ++c) fill[c] = start[c];
        for (int64_t i = 0; i < n; ++i) order[fill[cell[i]]++] = i;
        free(fill);
    }
    for (int64_t i = 0; i < n; ++i) {
        const double xi = pos[3 * i], yi = pos[3 * i + 1], zi = pos[3 * i + 2];
        const int64_t graph = group[i] / C, own = group[i] % C;
        int64_t slot = 0;
        for (int64_t c = 0; c < C; ++c) {
            if (c == own) continue;
            const int64_t g = graph * C + c;
            int64_t found = 0;
            for (int dz = -1; dz <= 1; ++dz) {
                const int64_t z = cx[3 * i + 2] + dz;
                if (z < 0 || z >= dim[2]) continue;
                for (int dy = -1; dy <= 1; ++dy) {
                    const int64_t y = cx[3 * i + 1] + dy;
                    if (y < 0 || y >= dim[1]) continue;
                    int64_t x0 = cx[3 * i] - 1, x1 = cx[3 * i] + 1;
                    if (x0 < 0) x0 = 0;
                    if (x1 >= dim[0]) x1 = dim[0] - 1;
                    const int64_t row = g * per_group + (z * dim[1] + y) * dim[0];
                    const int64_t end = start[row + x1 + 1];
                    for (int64_t p = start[row + x0]; p < end; ++p) {
                        const int64_t j = order[p];
                        const double dx = pos[3 * j] - xi, dy_ = pos[3 * j + 1] - yi, dz_ = pos[3 * j + 2] - zi;
                        const double d2 = dx * dx + dy_ * dy_ + dz_ * dz_;
                        if (d2 > r2) continue;
                        /* insert (d2, j) into the sorted best list, lexicographic order */
                        int64_t at = found < k ? found : k;
                        while (at > 0 && (d2 < best_d[at - 1] || (d2 == best_d[at - 1] && j < best_j[at - 1])))
                            --at;
                        if (at >= k) continue;
                        int64_t last = found < k ? found : k - 1;
                        for (int64_t m = last; m > at; --m) {
                            best_d[m] = best_d[m - 1];
                            best_j[m] = best_j[m - 1];
                        }
                        best_d[at] = d2;
                        best_j[at] = j;
                        if (found < k) ++found;
                    }
                }
            }
            for (int64_t m = 0; m < k; ++m, ++slot) {
                nbr[i * width + slot] = m < found ? best_j[m] : i;
                mask[i * width + slot] = m < found;
            }
        }
    }
    free(cell); free(start); free(order); free(cx); free(best_d); free(best_j);
    return 0;
}
