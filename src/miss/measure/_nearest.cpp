// The sampled measurement's kernels (miss.measure._native), in native code: sample points on a
// surface, bin its triangles into a grid of cells, and find each point's exact distance to
// the nearest triangle. Built at install (setup.py) and called through ctypes, which
// releases the GIL for each call; a process that measures then needs no numba, whose
// start (0.6-0.9 s on the 2-core test machine) was most of what measuring added to a fresh
// `miss convert`.
//
// Each function is the numba kernel of the same name in miss/measure/_jit.py, operation for
// operation and in the same types (float32 corners are subtracted in float32, as numba
// does; everything else in float64), compiled without contraction into fused multiply-adds:
// the same figures to the bit (tests/test_measuring.py compares them).

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <exception>
#include <new>
#include <system_error>
#include <thread>
#include <vector>

namespace {

const double kSliver = 1e-20;  // miss.measure._jit._SLIVER
const double kInf = std::numeric_limits<double>::infinity();

// Python's max/min of floats as numba computes them: the first of equal ones.
inline double max3(double a, double b, double c) {
    double m = a;
    if (b > m) m = b;
    if (c > m) m = c;
    return m;
}

template <typename T>
inline T min3(T a, T b, T c) {
    T m = a;
    if (b < m) m = b;
    if (c < m) m = c;
    return m;
}

template <typename T>
inline T max3t(T a, T b, T c) {
    T m = a;
    if (b > m) m = b;
    if (c > m) m = c;
    return m;
}

// ((a*b + c*d) + e*f), in the wider of the two types, as numba's _dot.
template <typename A, typename B>
inline auto dot(A ax, A ay, A az, B bx, B by, B bz) -> decltype(ax * bx) {
    return ax * bx + ay * by + az * bz;
}

template <typename T>
inline double segment_sq(double px, double py, double pz, T ax, T ay, T az, T bx, T by, T bz) {
    T abx = bx - ax, aby = by - ay, abz = bz - az;
    double apx = px - ax, apy = py - ay, apz = pz - az;
    T length2 = dot(abx, aby, abz, abx, aby, abz);
    double t = 0.0;
    if (length2 != 0) {
        t = dot(abx, aby, abz, apx, apy, apz) / length2;
        t = std::min(std::max(t, 0.0), 1.0);
    }
    double qx = apx - t * abx, qy = apy - t * aby, qz = apz - t * abz;
    return dot(qx, qy, qz, qx, qy, qz);
}

// Ericson, Real-Time Collision Detection 5.1.5 (miss.measure._jit._triangle_sq).
template <typename T>
inline double triangle_sq(double px, double py, double pz, T ax, T ay, T az, T bx, T by, T bz,
                          T cx, T cy, T cz) {
    T abx = bx - ax, aby = by - ay, abz = bz - az;
    T acx = cx - ax, acy = cy - ay, acz = cz - az;
    T nx = aby * acz - abz * acy, ny = abz * acx - abx * acz, nz = abx * acy - aby * acx;
    T scale = dot(abx, aby, abz, abx, aby, abz) * dot(acx, acy, acz, acx, acy, acz);
    if (double(dot(nx, ny, nz, nx, ny, nz)) <= kSliver * scale || scale == 0) {
        double e1 = segment_sq(px, py, pz, ax, ay, az, bx, by, bz);
        double e2 = segment_sq(px, py, pz, bx, by, bz, cx, cy, cz);
        double e3 = segment_sq(px, py, pz, cx, cy, cz, ax, ay, az);
        double m = e1;
        if (e2 < m) m = e2;
        if (e3 < m) m = e3;
        return m;
    }
    double apx = px - ax, apy = py - ay, apz = pz - az;
    double d1 = dot(abx, aby, abz, apx, apy, apz), d2 = dot(acx, acy, acz, apx, apy, apz);
    if (d1 <= 0.0 && d2 <= 0.0) return dot(apx, apy, apz, apx, apy, apz);
    double bpx = px - bx, bpy = py - by, bpz = pz - bz;
    double d3 = dot(abx, aby, abz, bpx, bpy, bpz), d4 = dot(acx, acy, acz, bpx, bpy, bpz);
    if (d3 >= 0.0 && d4 <= d3) return dot(bpx, bpy, bpz, bpx, bpy, bpz);
    double cpx = px - cx, cpy = py - cy, cpz = pz - cz;
    double d5 = dot(abx, aby, abz, cpx, cpy, cpz), d6 = dot(acx, acy, acz, cpx, cpy, cpz);
    if (d6 >= 0.0 && d5 <= d6) return dot(cpx, cpy, cpz, cpx, cpy, cpz);
    double vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
    double s, t;
    if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
        s = d1 / (d1 - d3);
        t = 0.0;
    } else if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
        s = 0.0;
        t = d2 / (d2 - d6);
    } else if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
        double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        s = 1.0 - w;
        t = w;
    } else {
        double denom = va + vb + vc;
        s = vb / denom;
        t = vc / denom;
    }
    double qx = apx - s * abx - t * acx, qy = apy - s * aby - t * acy;
    double qz = apz - s * abz - t * acz;
    return dot(qx, qy, qz, qx, qy, qz);
}

// max(low - p, p - high, 0) squared: maxsd twice, no branches (the same value as
// Python's max for numbers)
inline double box_sq(double p, double low, double high) {
    double a = low - p, b = p - high;
    double g = a > b ? a : b;
    g = g > 0.0 ? g : 0.0;
    return g * g;
}

inline double gap(double v, int64_t idx, double lo, double cell) {
    return max3(lo + double(idx) * cell - v, v - lo - double(idx + 1) * cell, 0.0);
}

inline int64_t home(double v, double lo, double cell, int64_t n) {
    int64_t h = int64_t((v - lo) / cell);  // truncated toward zero, as int()
    return std::max<int64_t>(0, std::min<int64_t>(h, n - 1));
}

inline double margin(double v, int64_t h, int64_t r, double lo, double cell, int64_t n, double m) {
    if (h - r > 0) m = std::min(m, v - (lo + double(h - r) * cell));
    if (h + r < n - 1) m = std::min(m, lo + double(h + r + 1) * cell - v);
    return m;
}

// A triangle's row: its corners a, b, c (x, y, z each), as numba's grid has them (so that
// either search takes either grid). A row with the box after the corners (16 numbers, a
// cache line of float32) searched about 10 % faster, but took 28 bytes a triangle more:
// 235 MB more for an 8.4-million-triangle MR head, measured in the command's own process.
const int64_t kRow = 9;

template <typename T>
struct Grid {
    double lo[3];
    double cell;
    int64_t dims[3];
    const int32_t* offsets;
    const int32_t* items;
    const T* tri;  // (F, kRow)
};

template <typename T>
inline double cell_sq(double px, double py, double pz, int64_t c, double best, const Grid<T>& g) {
    for (int32_t n = g.offsets[c]; n < g.offsets[c + 1]; ++n) {
        const T* r = g.tri + int64_t(g.items[n]) * kRow;
        // squared distance to the triangle's box: most are dismissed on that alone
        double d = box_sq(px, min3(r[0], r[3], r[6]), max3t(r[0], r[3], r[6]));
        d += box_sq(py, min3(r[1], r[4], r[7]), max3t(r[1], r[4], r[7]));
        d += box_sq(pz, min3(r[2], r[5], r[8]), max3t(r[2], r[5], r[8]));
        if (d < best) {
            double t = triangle_sq(px, py, pz, r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]);
            best = t < best ? t : best;
            if (best == 0.0) break;
        }
    }
    return best;
}

// miss.measure._jit._nearest_sq
template <typename T>
double nearest_sq(double px, double py, double pz, const Grid<T>& g, double cap2) {
    const double lox = g.lo[0], loy = g.lo[1], loz = g.lo[2], cell = g.cell;
    const int64_t nx = g.dims[0], ny = g.dims[1], nz = g.dims[2];
    int64_t hx = home(px, lox, cell, nx), hy = home(py, loy, cell, ny), hz = home(pz, loz, cell, nz);
    double best = cell_sq(px, py, pz, (hz * ny + hy) * nx + hx, kInf, g);
    int64_t r = 0;
    while (true) {
        double m = margin(px, hx, r, lox, cell, nx, kInf);
        m = margin(py, hy, r, loy, cell, ny, m);
        m = margin(pz, hz, r, loz, cell, nz, m);
        if (m == kInf || best <= m * m || m * m > cap2) return best;
        r += 1;
        for (int64_t k = std::max<int64_t>(hz - r, 0); k <= std::min(hz + r, nz - 1); ++k) {
            double gk = gap(pz, k, loz, cell);
            gk = gk * gk;
            if (gk >= best) continue;
            for (int64_t j = std::max<int64_t>(hy - r, 0); j <= std::min(hy + r, ny - 1); ++j) {
                double gy = gap(py, j, loy, cell);
                double gj = gk + gy * gy;
                if (gj >= best) continue;
                int64_t step = (std::llabs(k - hz) == r || std::llabs(j - hy) == r) ? 1 : 2 * r;
                for (int64_t i = hx - r; i < hx + r + 1; i += step) {
                    if (0 <= i && i < nx) {
                        double gx = gap(px, i, lox, cell);
                        double gg = gj + gx * gx;
                        if (gg < best) best = cell_sq(px, py, pz, (k * ny + j) * nx + i, best, g);
                    }
                }
            }
        }
    }
}

// miss.measure._jit._block_order
void block_order(const double* points, int64_t n, const double* lo, double cell,
                 const int64_t* dims, int64_t* order) {
    const int64_t side = 2;
    int64_t bx = (dims[0] + side - 1) / side, by = (dims[1] + side - 1) / side;
    int64_t bz = (dims[2] + side - 1) / side;
    std::vector<int64_t> keys(n), start(bx * by * bz + 1, 0);
    for (int64_t q = 0; q < n; ++q) {
        int64_t hx = home(points[3 * q], lo[0], cell, dims[0]);
        int64_t hy = home(points[3 * q + 1], lo[1], cell, dims[1]);
        int64_t hz = home(points[3 * q + 2], lo[2], cell, dims[2]);
        keys[q] = ((hz / side) * by + hy / side) * bx + hx / side;
        start[keys[q] + 1] += 1;
    }
    for (size_t c = 1; c < start.size(); ++c) start[c] += start[c - 1];
    for (int64_t q = 0; q < n; ++q) order[start[keys[q]]++] = q;
}

template <typename T>
void distances(const double* points, int64_t n, const Grid<T>& g, double cap2, int ordered,
               int threads, double* out) {
    std::vector<int64_t> order;
    std::vector<double> found;
    double* into = out;
    if (!ordered) {
        order.resize(n);
        block_order(points, n, g.lo, g.cell, g.dims, order.data());
        found.resize(n);
        into = found.data();
    }
    const int64_t* ord = ordered ? nullptr : order.data();
    // threads take chunks of consecutive queries in turn: neighbours stay together, and
    // each writes its answers in search order (see miss.measure._jit._grid_distances)
    const int64_t chunk = 512;
    std::atomic<int64_t> next(0);
    auto work = [&]() {
        while (true) {
            int64_t s = next.fetch_add(chunk);
            if (s >= n) return;
            int64_t e = std::min(s + chunk, n);
            for (int64_t m = s; m < e; ++m) {
                int64_t q = ord ? ord[m] : m;
                const double* p = points + 3 * q;
                into[m] = std::sqrt(nearest_sq(p[0], p[1], p[2], g, cap2));
            }
        }
    };
    threads = int(std::max<int64_t>(1, std::min<int64_t>(threads, (n + chunk - 1) / chunk)));
    std::vector<std::thread> pool;
    try {
        for (int t = 1; t < threads; ++t) pool.emplace_back(work);
    } catch (const std::system_error&) {
        // no thread to be had (a process's limits): the ones started and this one do it all
    }
    work();
    for (auto& t : pool) t.join();
    if (!ordered)
        for (int64_t m = 0; m < n; ++m) out[ord[m]] = found[m];
}

// miss.measure._jit._corners: (F, kRow) rows of corners. In the triangles' own order:
// the search visits a cell's triangles in that order, as numba's does, and so meets the same
// ties (a float32 triangle's distance, its edges taken in float32, may come out a hair below
// its box's, and then which of two triangles at one corner is measured first decides the
// last bit).
template <typename T>
void corners(const T* verts, const int32_t* faces, int64_t nf, T* out) {
    for (int64_t f = 0; f < nf; ++f) {
        T* row = out + kRow * f;
        for (int axis = 0; axis < 3; ++axis) {
            T a = verts[3 * int64_t(faces[3 * f]) + axis];
            T b = verts[3 * int64_t(faces[3 * f + 1]) + axis];
            T c = verts[3 * int64_t(faces[3 * f + 2]) + axis];
            row[axis] = a;
            row[3 + axis] = b;
            row[6 + axis] = c;
        }
    }
}

// The first and last cell along x, y, z that a row's box meets (miss.measure._jit._corners's
// spans, from the same numbers: made again here rather than kept, 24 bytes a triangle).
template <typename T>
inline void span_of(const T* row, const double* lo, double cell, const int64_t* dims,
                    int64_t* s) {
    for (int axis = 0; axis < 3; ++axis) {
        T a = row[axis], b = row[3 + axis], c = row[6 + axis];
        int64_t first = int64_t((min3(a, b, c) - lo[axis]) / cell);
        int64_t last = int64_t((max3t(a, b, c) - lo[axis]) / cell);
        s[axis] = std::max<int64_t>(0, std::min(first, dims[axis] - 1));
        s[3 + axis] = std::max<int64_t>(0, std::min(last, dims[axis] - 1));
    }
}

// miss.measure._jit._build_grid: with ``items`` null, each cell's count of triangles
// (offsets[c + 1], offsets zeroed), then their running sum; else each cell's triangles into
// items (offsets[-1] long), in triangle order.
template <typename T>
void grid_cells(const T* rows, int64_t nf, const double* lo, double cell, const int64_t* dims,
                int32_t* offsets, int32_t* items) {
    int64_t cells = dims[0] * dims[1] * dims[2];
    std::vector<int32_t> fill;
    if (items) fill.assign(offsets, offsets + cells);
    int64_t s[6];
    for (int64_t f = 0; f < nf; ++f) {
        span_of(rows + kRow * f, lo, cell, dims, s);
        for (int64_t k = s[2]; k <= s[5]; ++k)
            for (int64_t j = s[1]; j <= s[4]; ++j) {
                int64_t row = (k * dims[1] + j) * dims[0];
                for (int64_t c = row + s[0]; c <= row + s[3]; ++c) {
                    if (items)
                        items[fill[c]++] = int32_t(f);
                    else
                        offsets[c + 1] += 1;
                }
            }
    }
    if (!items)
        for (int64_t c = 1; c <= cells; ++c) offsets[c] += offsets[c - 1];
}

// miss.measure._jit._cumulative_areas
template <typename T>
void cumulative_areas(const T* verts, const int32_t* faces, int64_t nf, double* out) {
    double total = 0.0;
    for (int64_t f = 0; f < nf; ++f) {
        const T* a = verts + 3 * int64_t(faces[3 * f]);
        const T* b = verts + 3 * int64_t(faces[3 * f + 1]);
        const T* c = verts + 3 * int64_t(faces[3 * f + 2]);
        double ux = double(b[0]) - a[0], uy = double(b[1]) - a[1], uz = double(b[2]) - a[2];
        double vx = double(c[0]) - a[0], vy = double(c[1]) - a[1], vz = double(c[2]) - a[2];
        double nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
        total += std::sqrt(nx * nx + ny * ny + nz * nz);
        out[f] = total;
    }
}

// miss.measure._jit._inner_points
template <typename T>
void inner_points(const T* verts, const int32_t* faces, const double* cum, int64_t ncum,
                  const double* target, const int64_t* order, const double* r1,
                  const double* r2, const int64_t* slots, int64_t n, double* out) {
    int64_t f = 0;
    for (int64_t j = 0; j < n; ++j) {
        int64_t i = order[j];
        while (f < ncum - 1 && cum[f] <= target[i]) ++f;
        double s = r1[i], t = r2[i];
        if (s + t > 1) {
            s = 1 - s;
            t = 1 - t;
        }
        const T* a = verts + 3 * int64_t(faces[3 * f]);
        const T* b = verts + 3 * int64_t(faces[3 * f + 1]);
        const T* c = verts + 3 * int64_t(faces[3 * f + 2]);
        for (int k = 0; k < 3; ++k) {
            double ak = double(a[k]);
            out[3 * slots[j] + k] = ak + s * (double(b[k]) - ak) + t * (double(c[k]) - ak);
        }
    }
}

}  // namespace

// Runs ``work``; 0, or 1 where it ran out of memory (an exception must not cross into
// ctypes: the process would end).
template <typename F>
int guarded(F work) {
    try {
        work();
        return 0;
    } catch (const std::exception&) {  // bad_alloc, or length_error for a size past any
        return 1;
    }
}

extern "C" {

// The vertices some face uses, as 0/1 bytes (miss.measure._jit._used).
void miss_used(const int32_t* faces, int64_t nf, uint8_t* out) {
    for (int64_t f = 0; f < nf; ++f)
        for (int k = 0; k < 3; ++k) out[faces[3 * f + k]] = 1;
}

// miss.measure._jit._increasing: the order of values (uniform in [0, top]) by bucket.
int miss_increasing(const double* values, int64_t n, double top, int64_t* order) try {
    double scale = top > 0 ? double(n) / top : 0.0;
    std::vector<int64_t> bucket(n), start(n + 1, 0);
    for (int64_t i = 0; i < n; ++i) {
        bucket[i] = std::min<int64_t>(int64_t(values[i] * scale), n - 1);
        start[bucket[i] + 1] += 1;
    }
    for (int64_t b = 1; b <= n; ++b) start[b] += start[b - 1];
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t i = 0; i < n; ++i) order[fill[bucket[i]]++] = i;
    for (int64_t b = 0; b < n; ++b) {
        for (int64_t j = start[b] + 1; j < start[b + 1]; ++j) {
            int64_t i = order[j], m = j;
            while (m > start[b] && values[order[m - 1]] > values[i]) {
                order[m] = order[m - 1];
                --m;
            }
            order[m] = i;
        }
    }
    return 0;
} catch (const std::exception&) {  // see guarded
    return 1;
}

#define MISS_TYPED(T, SFX)                                                                    \
    void miss_corners_##SFX(const T* verts, const int32_t* faces, int64_t nf, T* out) {       \
        corners<T>(verts, faces, nf, out);                                                    \
    }                                                                                         \
    int miss_grid_cells_##SFX(const T* rows, int64_t nf, const double* lo, double cell,       \
                              const int64_t* dims, int32_t* offsets, int32_t* items) {        \
        return guarded([&] { grid_cells<T>(rows, nf, lo, cell, dims, offsets, items); });     \
    }                                                                                         \
    void miss_cumulative_areas_##SFX(const T* verts, const int32_t* faces, int64_t nf,        \
                                     double* out) {                                           \
        cumulative_areas<T>(verts, faces, nf, out);                                           \
    }                                                                                         \
    void miss_inner_points_##SFX(const T* verts, const int32_t* faces, const double* cum,     \
                                 int64_t ncum, const double* target, const int64_t* order,    \
                                 const double* r1, const double* r2, const int64_t* slots,    \
                                 int64_t n, double* out) {                                    \
        inner_points<T>(verts, faces, cum, ncum, target, order, r1, r2, slots, n, out);       \
    }                                                                                         \
    int miss_distances_##SFX(const double* points, int64_t n, const double* lo, double cell,  \
                              const int64_t* dims, const int32_t* offsets, const int32_t* items, \
                              const T* tri, double cap2, int ordered, int threads, double* out) { \
        Grid<T> g{{lo[0], lo[1], lo[2]}, cell, {dims[0], dims[1], dims[2]}, offsets, items, tri}; \
        return guarded([&] { distances<T>(points, n, g, cap2, ordered, threads, out); });     \
    }

MISS_TYPED(float, f32)
MISS_TYPED(double, f64)

}  // extern "C"

// A module of no functions: Python imports it (so that it is this interpreter's build),
// then calls the functions above through ctypes.
static struct PyModuleDef nearest_module = {
    PyModuleDef_HEAD_INIT, "_nearest", "MISS's measurement kernels, called through ctypes.", -1,
    nullptr, nullptr, nullptr, nullptr, nullptr};

PyMODINIT_FUNC PyInit__nearest(void) { return PyModule_Create(&nearest_module); }
