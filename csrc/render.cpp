#include "render.h"

#include "wavefront.h"

#include <array>
#include <atomic>
#include <cassert>
#include <memory>
#include <mutex>

namespace rbpt {

namespace {

/// Square tiles of the crop window, the unit of work. Tiles are numbered from the crop
/// window's corner whatever rows a render asks for, so a band of rows sums every pixel's
/// splats in the same order as the whole image does.
struct Tiles {
    int size = 16;  ///< edge in pixels
    int nx = 0, ny = 0;
    /// Tile (tx, ty)'s number, its place in the order in which tiles' borders are merged.
    int index(int tx, int ty) const { return ty * nx + tx; }
};

Tiles tiles_of(const Camera &camera) {
    Tiles t;
    t.size = std::max(16, 2 * camera.filter.border());  // borders at most half the tile
    t.nx = (camera.crop_width + t.size - 1) / t.size;
    t.ny = (camera.crop_height + t.size - 1) / t.size;
    return t;
}

/// A range [begin, end) of rows (of pixels, or of tiles).
struct RowRange {
    int begin, end;
};

/// The rows of tiles that meet the pixel rows `rows`.
RowRange tile_rows(const Tiles &tiles, RowRange rows) {
    int begin = rows.begin / tiles.size;
    return {begin, std::max(begin, (rows.end + tiles.size - 1) / tiles.size)};
}

/// The rows of the crop window a render asks for.
RowRange requested_rows(const Camera &camera, const RenderRequest &req) {
    return {req.row_begin, req.row_end < 0 ? camera.crop_height : req.row_end};
}

/// The rows whose samples reach `rows`: widened by the filter border, clipped to the window.
RowRange rows_reaching(const Camera &camera, RowRange rows) {
    int b = camera.filter.border();
    return {std::max(0, rows.begin - b), std::min(camera.crop_height, rows.end + b)};
}

/// Rows of the crop window whose samples a render traces: the requested rows and those whose
/// splats reach them.
RowRange sample_rows(const Camera &camera, const RenderRequest &req) {
    return rows_reaching(camera, requested_rows(camera, req));
}

/// Run f(tx, ty, count) for groups of consecutive tiles (in tile order; tx, ty the count
/// tiles' coordinates) meeting rows [rows.begin, rows.end) of the crop window, on all of
/// the pool's workers, each taking the next group when it is done with one. Tiles splat
/// into private buffers (Film::Block), so the order they run in changes no sum. A group is
/// at most `most` tiles and at most a quarter of the tiles left per worker, so that the
/// last groups are single tiles and the workers end together.
template <typename F>
void for_each_tile_group(const Tiles &tiles, RowRange rows, const WorkerPool &pool, int64_t most, F f) {
    RowRange ty = tile_rows(tiles, rows);
    const int64_t n = int64_t(tiles.nx) * (ty.end - ty.begin), quarter = 4 * std::max(pool.workers, 1);
    std::mutex taking;
    int64_t next = 0;
    auto take = [&](int64_t &begin, int64_t &end) {
        std::lock_guard<std::mutex> lock(taking);
        begin = next;
        end = next = std::min(n, next + std::clamp<int64_t>((n - next) / quarter, 1, std::max<int64_t>(most, 1)));
        return begin < n;
    };
    pool.run([&] {
        std::vector<int> xs, ys;
        for (int64_t begin, end; take(begin, end);) {
            xs.clear(), ys.clear();
            for (int64_t k = begin; k < end; ++k) xs.push_back(int(k % tiles.nx)), ys.push_back(ty.begin + int(k / tiles.nx));
            f(xs.data(), ys.data(), int(xs.size()));
        }
    });
}

/// for_each_tile_group() one tile at a time: tile(tx, ty).
template <typename F>
void for_each_tile(const Tiles &tiles, RowRange rows, const WorkerPool &pool, F tile) {
    for_each_tile_group(tiles, rows, pool, 1, [&](const int *tx, const int *ty, int count) {
        for (int i = 0; i < count; ++i) tile(tx[i], ty[i]);
    });
}

/// Pixels of tile (tx, ty) within `rows`, in film coordinates: f(px, py, key) for each.
template <typename F>
void for_each_pixel_of_tile(const Camera &camera, const Tiles &tiles, RowRange rows, int tx,
                            int ty, F pixel) {
    int x0 = tx * tiles.size, x1 = std::min(camera.crop_width, x0 + tiles.size);
    int y0 = std::max(rows.begin, ty * tiles.size);
    int y1 = std::min(rows.end, (ty + 1) * tiles.size);
    for (int y = y0; y < y1; ++y) {
        for (int x = x0; x < x1; ++x) {
            int px = camera.crop_x + x, py = camera.crop_y + y;
            pixel(px, py, uint64_t(py) * uint64_t(camera.film_width) + uint64_t(px));
        }
    }
}

/// Trace the camera path of a sample at film position `pos`, continuing `sampler`'s stream.
template <typename S>
S trace(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
        Vec2 pos, Sampler &sampler) {
    return li(ctx, cfg, camera.sample_ray(pos, sampler), sampler);
}

/// Whether a sample's value (and tangent, for dual numbers) is finite.
template <typename T>
bool sample_is_finite(const RGB<T> &L) {
    return SpectrumTraits<RGB<T>>::is_finite(L);
}
template <typename T>
bool sample_is_finite(const Dual<T> &L) {
    return SpectrumTraits<RGB<T>>::is_finite(L.v) && SpectrumTraits<RGB<T>>::is_finite(L.d);
}

template <typename S>
struct IsDual : std::false_type {};
template <typename T>
struct IsDual<Dual<T>> : std::true_type {};

/// Weighted sums of the samples splatted into one pixel: value (r, g, b) and weight side by
/// side, so that a splat adds one 4-wide vector w (L, 1) per pixel.
struct alignas(32) PixelSum {
    double value[3] = {0.0, 0.0, 0.0};
    double weight = 0.0;
};

/// A PixelSum as one 4-wide vector (GCC's vector type), so that adding w (r, g, b, 1) is a
/// broadcast, a product and a sum (the vectoriser built the broadcast from shuffles).
typedef double Sum4 __attribute__((vector_size(32)));
/// Eight doubles: a channel of a row of up to eight pixels (Film::splat_run).
typedef double Row8 __attribute__((vector_size(64)));
static_assert(sizeof(PixelSum) == sizeof(Sum4));
inline Sum4 load_sum(const PixelSum &s) { return Sum4{s.value[0], s.value[1], s.value[2], s.weight}; }
inline void store_sum(PixelSum &s, const Sum4 &v) {
    for (int c = 0; c < 3; ++c) s.value[c] = v[c];
    s.weight = v[3];
}

/// A rectangle [x0, x1) x [y0, y1) of the crop window.
struct Rect {
    int x0 = 0, y0 = 0, x1 = 0, y1 = 0;
    bool contains(int x, int y) const { return x >= x0 && x < x1 && y >= y0 && y < y1; }
    int width() const { return x1 - x0; }
    size_t area() const { return x1 > x0 && y1 > y0 ? size_t(x1 - x0) * size_t(y1 - y0) : 0; }
};

/// The filter weights of a batch of samples, computed for all of them at once
/// (Filter::eval_rows: the tent's and the gaussian's in SIMD lanes): row weight i of sample k
/// at wx[i * Batch + k] (i < 2 border() + 1), likewise wy, and how many of each row's
/// weights are zero at its start and end (at most border()), counted in lanes too. The
/// wavefront's film splats with them; the backward pass sums its weights and gathers its
/// adjoints with them.
struct SplatWeights {
    static constexpr int Batch = 256;
    const Filter &filter;
    const int b, rows;
    std::vector<float> wx, wy;
    /// Each sample's row starts in x and y (Camera::splat_row_start): set them, then compute().
    alignas(64) float x0[Batch], y0[Batch];
    /// The zero weights at the start and end of x's rows, then of y's, and whether all those
    /// counted so far were zero.
    alignas(64) int zeros[4][Batch], all_zero[4][Batch];

    explicit SplatWeights(const Filter &f)
        : filter(f), b(f.border()), rows(2 * b + 1), wx(size_t(rows) * Batch, 1.f), wy(wx.size(), 1.f) {
        std::fill_n(&zeros[0][0], 4 * Batch, 0);  // (the box: its one weight is 1)
    }
    /// Sample k's row start for a sample at pos taken in pixel (px, py).
    void set(int k, int px, int py, Vec2 pos) {
        x0[k] = Camera::splat_row_start(px, b, pos.x);
        y0[k] = Camera::splat_row_start(py, b, pos.y);
    }
    /// The weights and zero counts of samples [0, n).
    void compute(int n) {
        if (b == 0) return;
        filter.eval_rows(x0, n, rows, wx.data(), Batch);
        filter.eval_rows(y0, n, rows, wy.data(), Batch);
        std::fill_n(&zeros[0][0], 4 * Batch, 0);
        std::fill_n(&all_zero[0][0], 4 * Batch, 1);
        for (int t = 0; t < b; ++t) {  // (a pass per offset)
            const float *ends[4] = {&wx[size_t(t) * Batch], &wx[size_t(rows - 1 - t) * Batch],
                                    &wy[size_t(t) * Batch], &wy[size_t(rows - 1 - t) * Batch]};
            for (int e = 0; e < 4; ++e) {
                const float *w = ends[e];
                int *count = zeros[e], *all = all_zero[e];
#pragma GCC ivdep
                for (int k = 0; k < n; ++k) {
                    all[k] &= int(w[k] == 0.f);
                    count[k] += all[k];
                }
            }
        }
    }
};

// (GCC 12 takes the unset pass-through operand of some AVX-512 intrinsics, as the film's
// _mm512_insertf64x4, for an uninitialised variable, depending on how far it inlines the
// functions below: GCC bug 105593, fixed in GCC 13. Until the end of the file.)
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"

/// The film of one render: a PixelSum per pixel of the requested rows, and the weighted sums
/// of the samples' tangents when it splats dual numbers. A tile splats its samples into a
/// Block of its own, covering the tile and the border its splats reach (its neighbours'
/// pixels: a border is at most half a tile). commit() moves the tile's own pixels into the
/// film and keeps the border until its turn: borders are added in tile order, each once the
/// tiles whose pixels it covers are committed. Every pixel is thus its own tile's sum plus
/// its neighbours' borders in a fixed order, whatever order the threads ran the tiles in, and
/// only the borders of about a row of tiles wait at any time.
class Film {
public:
    /// Pixel sums over a rectangle of the crop window.
    struct Block {
        Rect rect;
        std::vector<PixelSum> sums;
        std::vector<RGB<double>> tangents;  ///< empty unless the film sums tangents
        size_t index(int x, int y) const { return size_t(y - rect.y0) * rect.width() + size_t(x - rect.x0); }
    };

    /// A film over `rows`, splatted tile by tile; with `tangents`, it also sums the tangents of
    /// dual-number samples.
    Film(const Camera &camera, const Tiles &tiles, RowRange rows, bool tangents = false)
        : camera_(camera), tiles_(tiles), rows_(rows), tangents_(tangents),
          borders_(size_t(tiles.nx) * size_t(tiles.ny)), committed_(borders_.size(), 0) {
        image_.rect = {0, rows.begin, camera.crop_width, rows.end};
        image_.sums.resize(image_.rect.area());
        if (tangents) image_.tangents.resize(image_.sums.size());
        // The tiles whose samples reach these rows (those for_each_tile runs over sample_rows).
        RowRange ty = tile_rows(tiles, rows_reaching(camera, rows));
        ty_begin_ = ty.begin;
        ty_end_ = ty.end;
        next_border_ = tiles.index(0, ty_begin_);
    }

    /// A zeroed block for the samples of tile (tx, ty).
    Block block(int tx, int ty) const {
        Block block;
        block.rect = block_rect(tx, ty);
        block.sums.resize(block.rect.area());
        if (tangents_) block.tangents.resize(block.sums.size());
        return block;
    }

    /// Splat a sample taken in pixel (px, py) of tile (tx, ty) at `pos` (film coordinates) into
    /// that tile's block; with L null, only its weights (for the backward pass's
    /// normalisation). It reaches the pixels for_each_reached reaches.
    template <typename S>
    void splat(Block &block, int px, int py, Vec2 pos, const S *L) const {
        Footprint fp = footprint(px, py, pos);
        add(block, fp, fp.wx, fp.wy, 1, L);
    }
    /// splat() of sample k of `w`, taken in pixel (px, py): the same pixels and sums, up to
    /// zero weights.
    template <typename S>
    void splat(Block &block, int px, int py, const SplatWeights &w, int k, const S *L) const {
        add(block, window(px, py, w, k), &w.wx[size_t(k)], &w.wy[size_t(k)], SplatWeights::Batch, L);
    }
    /// splat() of samples ks[0, r) of `w`, all taken in pixel (px, py), in that order, their
    /// values finite: each pixel of the filter's whole window adds them one after another,
    /// the sums splat() makes (a weight splat() skips is zero, and adding w L = +-0 leaves a
    /// sum unchanged: no sum is -0), with a row of sums held in registers over the run
    /// instead of loaded and stored per sample (veach-mis's gaussian: 4-5% of a render; the
    /// tent's nine sums, splat_run_tent: the film's samples a fifth to a third fewer, 1 to 64
    /// spp). Windows the film's edges cut, and wider filters', take splat().
    void splat_run(Block &block, int px, int py, const SplatWeights &w, const int *ks, int r,
                   const RGB<float> *L) const {
        const Window win = window(px, py, 0, 0, 0, 0);
        const bool whole = win.whole();
        if (whole && win.b == 1) return splat_run_tent(block, win, w, ks, r, L);
        if (whole && win.b == 2) return splat_run<2>(block, win, w, ks, r, L);
        if (whole && win.b == 3) return splat_run<3>(block, win, w, ks, r, L);
        for (int s = 0; s < r; ++s) splat(block, px, py, w, ks[s], &L[ks[s]]);
    }

    /// splat() of the weights alone (L null) of samples [0, n) of `w`, all taken in pixel
    /// (px, py), in that order: over a whole window, each pixel's weight sum held in a register
    /// over the run (the backward pass's sums W_p, a pixel's samples in one run).
    void splat_weights(Block &block, int px, int py, const SplatWeights &w, int n) const {
        const Window win = window(px, py, 0, 0, 0, 0);
        const int b = win.b, N = 2 * b + 1;
        if (!win.whole() || N > 8) {
            for (int k = 0; k < n; ++k) splat<RGB<float>>(block, px, py, w, k, nullptr);
            return;
        }
        constexpr size_t Batch = SplatWeights::Batch;
        for (int j = 0; j < N; ++j) {
            PixelSum *sum = &block.sums[block.index(win.x - b, win.y + j - b)];
            double acc[8];
            for (int i = 0; i < N; ++i) acc[i] = sum[i].weight;
            const float *wy = &w.wy[size_t(j) * Batch];
            for (int k = 0; k < n; ++k)
                for (int i = 0; i < N; ++i) acc[i] += double(w.wx[size_t(i) * Batch + size_t(k)]) * double(wy[k]);
            for (int i = 0; i < N; ++i) sum[i].weight = acc[i];
        }
    }

    /// Move tile (tx, ty)'s block into the film: its own pixels now, its border when its turn
    /// comes (see the class). Distinct tiles may commit concurrently.
    void commit(int tx, int ty, Block &&block) {
        Rect own = own_rect(tx, ty);
        for (int y = own.y0; y < own.y1; ++y) {
            for (int x = own.x0; x < own.x1; ++x) {
                image_.sums[image_.index(x, y)] = block.sums[block.index(x, y)];
                if (tangents_) image_.tangents[image_.index(x, y)] = block.tangents[block.index(x, y)];
            }
        }
        Border &border = borders_[tiles_.index(tx, ty)];
        border.sums.reserve(block.sums.size() - own.area());
        if (tangents_) border.tangents.reserve(border.sums.capacity());
        for_each_border_pixel(tx, ty, [&](int x, int y) {
            border.sums.push_back(block.sums[block.index(x, y)]);
            if (tangents_) border.tangents.push_back(block.tangents[block.index(x, y)]);
        });
        // Add the borders whose turn has come: the next in tile order, while the tiles its
        // block covers are all committed.
        std::lock_guard<std::mutex> lock(merge_mutex_);
        committed_[tiles_.index(tx, ty)] = 1;
        int end = tiles_.index(0, ty_end_);
        while (next_border_ < end && neighbours_committed(next_border_)) merge_border(next_border_++);
    }

    /// Whether every tile's border has been added (all tiles committed).
    bool complete() const { return next_border_ == tiles_.index(0, ty_end_); }

    /// Call f(i, w) for each pixel i (row-major over the film's rows) that a sample taken in
    /// pixel (px, py) at film position `pos` reaches, with its filter weight w (the
    /// footprint's edges have nonzero weights; a weight inside it may be zero).
    template <typename F>
    void for_each_reached(int px, int py, Vec2 pos, F f) const {
        Footprint fp = footprint(px, py, pos);
        for_each_in(fp, fp.wx, fp.wy, 1, f);
    }

    /// for_each_reached() of sample k of `w`, taken in pixel (px, py): the same pixels and
    /// weights, up to zero weights.
    template <typename F>
    void for_each_reached(int px, int py, const SplatWeights &w, int k, F f) const {
        for_each_in(window(px, py, w, k), &w.wx[size_t(k)], &w.wy[size_t(k)], SplatWeights::Batch, f);
    }

    /// Pixel i (row-major over the requested rows).
    const PixelSum &operator[](size_t i) const { return image_.sums[i]; }
    /// The weighted sum of the tangents splatted into pixel i (a film with `tangents`).
    const RGB<double> &tangent(size_t i) const { return image_.tangents[i]; }
    size_t size() const { return image_.sums.size(); }

private:
    /// A tile's sums for the pixels of its block outside the tile, in raster order.
    struct Border {
        std::vector<PixelSum> sums;
        std::vector<RGB<double>> tangents;
    };

    /// Whether tile k and those around it (whose pixels its block covers) are committed.
    bool neighbours_committed(int k) const {
        int tx = k % tiles_.nx, ty = k / tiles_.nx;
        for (int y = std::max(ty_begin_, ty - 1); y <= std::min(ty_end_ - 1, ty + 1); ++y)
            for (int x = std::max(0, tx - 1); x <= std::min(tiles_.nx - 1, tx + 1); ++x)
                if (!committed_[tiles_.index(x, y)]) return false;
        return true;
    }

    /// f(x, y) for each pixel of tile (tx, ty)'s block outside the tile itself, in raster
    /// order: the order its Border stores them in.
    template <typename F>
    void for_each_border_pixel(int tx, int ty, F f) const {
        Rect rect = block_rect(tx, ty), own = own_rect(tx, ty);
        for (int y = rect.y0; y < rect.y1; ++y)
            for (int x = rect.x0; x < rect.x1; ++x)
                if (!own.contains(x, y)) f(x, y);
    }

    /// Add tile k's border into the film and free it.
    void merge_border(int k) {
        Border &border = borders_[k];
        size_t i = 0;
        for_each_border_pixel(k % tiles_.nx, k / tiles_.nx, [&](int x, int y) {
            PixelSum &sum = image_.sums[image_.index(x, y)];
            for (int c = 0; c < 3; ++c) sum.value[c] += border.sums[i].value[c];
            sum.weight += border.sums[i].weight;
            if (tangents_) image_.tangents[image_.index(x, y)] += border.tangents[i];
            ++i;
        });
        border = Border();
    }

    /// Tile (tx, ty)'s own pixels within the film's rows.
    Rect own_rect(int tx, int ty) const {
        int x0 = tx * tiles_.size, y0 = ty * tiles_.size;
        return {x0, std::max(rows_.begin, y0), std::min(camera_.crop_width, x0 + tiles_.size),
                std::min(rows_.end, y0 + tiles_.size)};
    }
    /// The pixels within the film's rows that tile (tx, ty)'s samples reach.
    Rect block_rect(int tx, int ty) const {
        int b = camera_.filter.border(), x0 = tx * tiles_.size, y0 = ty * tiles_.size;
        return {std::max(0, x0 - b), std::max(rows_.begin, y0 - b),
                std::min(camera_.crop_width, x0 + tiles_.size + b), std::min(rows_.end, y0 + tiles_.size + b)};
    }

    /// The window of pixels a sample's splat covers, offsets [i0, i1] x [j0, j1] from the
    /// sample's pixel (x, y in the crop window), clipped to the film's columns and rows and to
    /// the weights that are not zero at its edges (a tent of radius 1 reaches 2 x 2 of its
    /// 3 x 3 pixels; what it skips would add zeros, which leave a sum unchanged).
    struct Window {
        int b, x, y, i0, i1, j0, j1;
        /// Whether it is the filter's whole window, uncut by the film's edges.
        bool whole() const { return i0 == -b && i1 == b && j0 == -b && j1 == b; }
    };
    /// A sample's filter weights and its window.
    struct Footprint : Window {
        float wx[2 * Filter::MaxBorder + 1], wy[2 * Filter::MaxBorder + 1];
    };
    Footprint footprint(int px, int py, Vec2 pos) const {
        Footprint fp;
        camera_.splat_weights(pos, px, py, fp.wx, fp.wy);
        static_cast<Window &>(fp) = window(px, py, 0, 0, 0, 0);
        // (Branch-free: which edge is zero is a coin flip per sample.)
        for (int t = 0; t < fp.b; ++t) {
            fp.i0 += int((fp.i0 < fp.i1) & (fp.wx[fp.i0 + fp.b] == 0.f));
            fp.i1 -= int((fp.i1 > fp.i0) & (fp.wx[fp.i1 + fp.b] == 0.f));
            fp.j0 += int((fp.j0 < fp.j1) & (fp.wy[fp.j0 + fp.b] == 0.f));
            fp.j1 -= int((fp.j1 > fp.j0) & (fp.wy[fp.j1 + fp.b] == 0.f));
        }
        return fp;
    }
    /// The window of sample k of `w`, taken in pixel (px, py).
    Window window(int px, int py, const SplatWeights &w, int k) const {
        return window(px, py, w.zeros[0][k], w.zeros[1][k], w.zeros[2][k], w.zeros[3][k]);
    }
    /// The window of a sample taken in pixel (px, py) whose weights start with `lead` zeros
    /// and end with `trail` (each at most border()) in x and in y, clipped to the film.
    Window window(int px, int py, int lead_x, int trail_x, int lead_y, int trail_y) const {
        Window win;
        win.b = camera_.filter.border();
        win.x = px - camera_.crop_x;
        win.y = py - camera_.crop_y;
        win.i0 = std::max(lead_x - win.b, -win.x);
        win.i1 = std::min(win.b - trail_x, camera_.crop_width - 1 - win.x);
        win.j0 = std::max(lead_y - win.b, rows_.begin - win.y);
        win.j1 = std::min(win.b - trail_y, rows_.end - 1 - win.y);
        return win;
    }

    /// f(i, w) for each pixel i of a window (row-major over the film's rows), with its weight
    /// w from wx[(i + b) * stride] and wy[(j + b) * stride].
    template <typename F>
    void for_each_in(const Window &win, const float *wx, const float *wy, size_t stride, F f) const {
        for (int j = win.j0; j <= win.j1; ++j) {
            size_t row = image_.index(win.x, win.y + j);
            for (int i = win.i0; i <= win.i1; ++i)
                f(row + i, double(wx[size_t(i + win.b) * stride]) * double(wy[size_t(j + win.b) * stride]));
        }
    }

    /// Add a sample's weighted value (and weight) into the pixels of its window, its weights
    /// at wx[(i + b) * stride] and wy[(j + b) * stride].
    template <typename S>
    void add(Block &block, const Window &win, const float *wx, const float *wy, size_t stride,
             const S *L) const {
        if constexpr (std::is_same_v<S, RGB<float>>) {
            if (L && win.i1 == win.i0 + 1 && win.j1 == win.j0 + 1) return add_2x2(block, win, wx, wy, stride, *L);
        }
        double l[4] = {0.0, 0.0, 0.0, 1.0};
        if (L) value_of(*L, l);
        const Sum4 l4 = {l[0], l[1], l[2], l[3]};
        for (int j = win.j0; j <= win.j1; ++j) {
            size_t row = block.index(win.x, win.y + j);
            PixelSum *sum = &block.sums[row];
            double wyj = wy[size_t(j + win.b) * stride];
            for (int i = win.i0; i <= win.i1; ++i) {
                double w = double(wx[size_t(i + win.b) * stride]) * wyj;
                store_sum(sum[i], load_sum(sum[i]) + w * l4);
            }
            if constexpr (IsDual<S>::value) {
                if (!L || block.tangents.empty()) continue;
                for (int i = win.i0; i <= win.i1; ++i) {
                    double w = double(wx[size_t(i + win.b) * stride]) * wyj;
                    for (int c = 0; c < 3; ++c) block.tangents[row + i][c] += w * double(L->d[c]);
                }
            }
        }
    }

    /// add() of a window of 2 x 2 pixels (the tent's, or any window cut to that) for a sample
    /// of value L: wy_j (wx_i l, wx_i+1 l) added to each row's two PixelSums, l = (r, g, b, 1),
    /// with AVX-512 as one vector of eight doubles. The same sums as add()'s: wx wy and wx l
    /// are exact in double, so wy (wx l) rounds once, as (wx wy) l does. (l is built in
    /// registers: a first version read it from an array just stored, and that
    /// store-forwarding stall took most of the gain.) Single thread, 256 px, 16 spp, against
    /// add()'s loop: AVX-512 cbox 1-3%, cornell-box 2-5%, glossy, textured and the bunny 1-2%
    /// faster; AVX2 about 1% (the unrolled sums: add()'s loop alone was 1% slower there).
    static void add_2x2(Block &block, const Window &win, const float *wx, const float *wy, size_t stride,
                        const RGB<float> &L) {
        const double wx0 = wx[size_t(win.i0 + win.b) * stride], wx1 = wx[size_t(win.i0 + 1 + win.b) * stride];
#if defined(__AVX512F__) && defined(__AVX512VL__)
        const __m128 l = _mm_mask_blend_ps(0x8, _mm_maskz_loadu_ps(0x7, L.v), _mm_set1_ps(1.f));
        const __m512d l2 = _mm512_broadcast_f64x4(_mm256_cvtps_pd(l));
        const __m512d q = _mm512_mul_pd(_mm512_insertf64x4(_mm512_castpd256_pd512(_mm256_set1_pd(wx0)), _mm256_set1_pd(wx1), 1), l2);
        for (int j = win.j0; j <= win.j1; ++j) {
            double *row = block.sums[block.index(win.x + win.i0, win.y + j)].value;
            const __m512d wyj = _mm512_set1_pd(double(wy[size_t(j + win.b) * stride]));
            _mm512_storeu_pd(row, _mm512_add_pd(_mm512_loadu_pd(row), _mm512_mul_pd(wyj, q)));
        }
#else
        const Sum4 l4 = {double(L[0]), double(L[1]), double(L[2]), 1.0};
        const Sum4 q0 = wx0 * l4, q1 = wx1 * l4;
        for (int j = win.j0; j <= win.j1; ++j) {
            PixelSum *sum = &block.sums[block.index(win.x + win.i0, win.y + j)];
            const double wyj = wy[size_t(j + win.b) * stride];
            store_sum(sum[0], load_sum(sum[0]) + wyj * q0);
            store_sum(sum[1], load_sum(sum[1]) + wyj * q1);
        }
#endif
    }

    /// splat_run() over the tent's whole 3 x 3 window: its nine sums held in registers over the
    /// run, each sample adding wy_j (wx_i l) to all nine (l = (r, g, b, 1); the weights
    /// outside the 2 x 2 pixels splat() reaches are zero, and adding zero leaves a sum
    /// unchanged), the products and sums add_2x2() makes, in its order. One sample after
    /// another, add_2x2() loaded a row's two sums as one 64-byte vector that the previous
    /// sample had stored at a 32-byte offset in half the runs (the pixel to the left or to the
    /// right), and such a partly overlapping load waits for the store to retire.
    void splat_run_tent(Block &block, const Window &win, const SplatWeights &w, const int *ks, int r,
                        const RGB<float> *L) const {
        constexpr size_t Batch = SplatWeights::Batch;
        PixelSum *row[3];
        for (int j = 0; j < 3; ++j) row[j] = &block.sums[block.index(win.x - 1, win.y + j - 1)];
        const float *wx = w.wx.data(), *wy = w.wy.data();
#if defined(__AVX512F__) && defined(__AVX512VL__)
        // Each row's first two sums as one vector, its third as another.
        __m512d a[3];
        __m256d c[3];
        for (int j = 0; j < 3; ++j) a[j] = _mm512_loadu_pd(row[j][0].value), c[j] = _mm256_loadu_pd(row[j][2].value);
        for (int s = 0; s < r; ++s) {
            const size_t k = size_t(ks[s]);
            const __m256d l = _mm256_cvtps_pd(_mm_mask_blend_ps(0x8, _mm_maskz_loadu_ps(0x7, L[k].v), _mm_set1_ps(1.f)));
            const __m512d wx01 = _mm512_insertf64x4(_mm512_castpd256_pd512(_mm256_set1_pd(double(wx[k]))),
                                                    _mm256_set1_pd(double(wx[Batch + k])), 1);
            const __m512d q = _mm512_mul_pd(wx01, _mm512_broadcast_f64x4(l));
            const __m256d q2 = _mm256_mul_pd(_mm256_set1_pd(double(wx[2 * Batch + k])), l);
            for (int j = 0; j < 3; ++j) {
                const double wyj = double(wy[size_t(j) * Batch + k]);
                a[j] = _mm512_add_pd(a[j], _mm512_mul_pd(_mm512_set1_pd(wyj), q));
                c[j] = _mm256_add_pd(c[j], _mm256_mul_pd(_mm256_set1_pd(wyj), q2));
            }
        }
        for (int j = 0; j < 3; ++j) _mm512_storeu_pd(row[j][0].value, a[j]), _mm256_storeu_pd(row[j][2].value, c[j]);
#else
        Sum4 a[3][3];
        for (int j = 0; j < 3; ++j)
            for (int i = 0; i < 3; ++i) a[j][i] = load_sum(row[j][i]);
        for (int s = 0; s < r; ++s) {
            const size_t k = size_t(ks[s]);
            const Sum4 l = {double(L[k][0]), double(L[k][1]), double(L[k][2]), 1.0};
            Sum4 q[3];
            for (int i = 0; i < 3; ++i) q[i] = double(wx[size_t(i) * Batch + k]) * l;
            for (int j = 0; j < 3; ++j) {
                const double wyj = double(wy[size_t(j) * Batch + k]);
                for (int i = 0; i < 3; ++i) a[j][i] += wyj * q[i];
            }
        }
        for (int j = 0; j < 3; ++j)
            for (int i = 0; i < 3; ++i) store_sum(row[j][i], a[j][i]);
#endif
    }

    /// splat_run() over a whole window of border Border (5 x 5: the gaussian's; 7 x 7), a row
    /// of the window's sums at a time held in registers over the run: the products and sums
    /// splat() makes, in its order. With AVX-512, one 8-wide vector per channel (and one
    /// for the weights) holds the row's pixels in its lanes, so that a sample adds its
    /// weights times its value to the whole row at once (veach-mis 84 -> 81-82 ms against a
    /// 4-wide vector per pixel); narrower builds keep a 4-wide vector per pixel (GCC splits
    /// the 8-wide vectors through memory there: veach-mis 127 -> 158 ms with AVX2).
    template <int Border>
    void splat_run(Block &block, const Window &win, const SplatWeights &w, const int *ks, int r,
                   const RGB<float> *L) const {
        constexpr int N = 2 * Border + 1;
        static_assert(N <= 8, "a row of the window in one vector");
        constexpr size_t Batch = SplatWeights::Batch;
#if defined(__AVX512F__)
        // Each sample's weights along x (zero beyond N) and value, in double.
        Row8 wx[Batch];
        double lr[Batch], lg[Batch], lb[Batch];
        for (int s = 0; s < r; ++s) {
            const size_t k = size_t(ks[s]);
            Row8 v = {};
            for (int i = 0; i < N; ++i) v[i] = double(w.wx[size_t(i) * Batch + k]);
            wx[s] = v;
            lr[s] = double(L[k][0]), lg[s] = double(L[k][1]), lb[s] = double(L[k][2]);
        }
        // The gaussian's five rows two at a time (each pixel's sum still adds the samples in
        // order): their sums' chains of additions side by side (veach-mis 3-4% faster; the
        // tent's three rows unchanged within noise, so they keep one at a time).
        int j = 0;
        for (; N >= 5 && j + 1 < N; j += 2) {
            PixelSum *sum0 = &block.sums[block.index(win.x - Border, win.y + j - Border)];
            PixelSum *sum1 = &block.sums[block.index(win.x - Border, win.y + j + 1 - Border)];
            Row8 ar, ag, ab, aw, br, bg, bb, bw;
            load_row<N>(sum0, ar, ag, ab, aw);
            load_row<N>(sum1, br, bg, bb, bw);
            const float *wy0 = &w.wy[size_t(j) * Batch], *wy1 = &w.wy[size_t(j + 1) * Batch];
            for (int s = 0; s < r; ++s) {
                const Row8 p = wx[s] * double(wy0[ks[s]]), q = wx[s] * double(wy1[ks[s]]);
                ar += p * lr[s], ag += p * lg[s], ab += p * lb[s], aw += p;  // (p's own: p * 1)
                br += q * lr[s], bg += q * lg[s], bb += q * lb[s], bw += q;
            }
            store_row<N>(sum0, ar, ag, ab, aw);
            store_row<N>(sum1, br, bg, bb, bw);
        }
        for (; j < N; ++j) {
            PixelSum *sum = &block.sums[block.index(win.x - Border, win.y + j - Border)];
            Row8 ar, ag, ab, aw;
            load_row<N>(sum, ar, ag, ab, aw);
            const float *wy = &w.wy[size_t(j) * Batch];
            for (int s = 0; s < r; ++s) {
                const Row8 p = wx[s] * double(wy[ks[s]]);
                ar += p * lr[s], ag += p * lg[s], ab += p * lb[s], aw += p;  // (p's own: p * 1)
            }
            store_row<N>(sum, ar, ag, ab, aw);
        }
#else
        for (int j = 0; j < N; ++j) {
            PixelSum *sum = &block.sums[block.index(win.x - Border, win.y + j - Border)];
            Sum4 acc[N];
            for (int i = 0; i < N; ++i) acc[i] = load_sum(sum[i]);
            for (int s = 0; s < r; ++s) {
                const size_t k = size_t(ks[s]);
                const double wy = w.wy[size_t(j) * Batch + k];
                const Sum4 l = {double(L[k][0]), double(L[k][1]), double(L[k][2]), 1.0};
                for (int i = 0; i < N; ++i) acc[i] += (double(w.wx[size_t(i) * Batch + k]) * wy) * l;
            }
            for (int i = 0; i < N; ++i) store_sum(sum[i], acc[i]);
        }
#endif
    }

#if defined(__AVX512F__)
    /// A row of N PixelSums (4 N doubles: r, g, b, weight of each pixel in turn) as one vector
    /// per channel, pixel i in lane i (the lanes from N on hold zeros or copies), by two-table
    /// permutes of the row's 8-double pieces (two pixels each). GCC's own transposes of
    /// element-wise copies went through the stack, and at 1 spp took over half of veach-mis's
    /// splats.
    template <int N>
    static void load_row(const PixelSum *row, Row8 &r, Row8 &g, Row8 &b, Row8 &w) {
        constexpr int Pieces = (N + 1) / 2;
        const double *p = row[0].value;
        __m512d m[4];
        for (int k = 0; k < 4; ++k)
            m[k] = k >= Pieces ? _mm512_setzero_pd()
                 : 2 * k + 2 <= N ? _mm512_loadu_pd(p + 8 * k) : _mm512_maskz_loadu_pd(0x0F, p + 8 * k);
        Row8 *channels[4] = {&r, &g, &b, &w};
        for (int c = 0; c < 4; ++c) {
            // Lane i (mod 4) takes element 4 i + c of two pieces.
            const __m512i idx = _mm512_add_epi64(_mm512_set_epi64(12, 8, 4, 0, 12, 8, 4, 0), _mm512_set1_epi64(c));
            __m512d v = _mm512_permutex2var_pd(m[0], idx, m[1]);
            if (N > 4) v = _mm512_mask_blend_pd(0xF0, v, _mm512_permutex2var_pd(m[2], idx, m[3]));
            *channels[c] = (Row8)v;
        }
    }
    /// load_row()'s inverse: pixels [0, N) of the channels back into the row.
    template <int N>
    static void store_row(PixelSum *row, const Row8 &r, const Row8 &g, const Row8 &b, const Row8 &w) {
        double *p = row[0].value;
        for (int k = 0; 2 * k < N; ++k) {
            // Piece k: pixels 2 k and 2 k + 1, r and g from one permute, b and w from another.
            const __m512i idx = _mm512_add_epi64(_mm512_set_epi64(9, 1, 9, 1, 8, 0, 8, 0), _mm512_set1_epi64(2 * k));
            const __m512d rg = _mm512_permutex2var_pd((__m512d)r, idx, (__m512d)g);
            const __m512d bw = _mm512_permutex2var_pd((__m512d)b, idx, (__m512d)w);
            const __m512d piece = _mm512_mask_blend_pd(0xCC, rg, bw);
            if (2 * k + 2 <= N) _mm512_storeu_pd(p + 8 * k, piece);
            else _mm512_mask_storeu_pd(p + 8 * k, 0x0F, piece);
        }
    }
#endif

    template <typename T>
    static void value_of(const RGB<T> &L, double *l) {
        for (int c = 0; c < 3; ++c) l[c] = double(L[c]);
    }
    template <typename T>
    static void value_of(const Dual<T> &L, double *l) {
        value_of(L.v, l);
    }

    const Camera &camera_;
    Tiles tiles_;
    RowRange rows_;
    bool tangents_;
    Block image_;
    std::vector<Border> borders_;  ///< per tile (Tiles::index), until its turn to be added
    int ty_begin_ = 0, ty_end_ = 0;  ///< the rows of tiles a render runs
    std::mutex merge_mutex_;         ///< guards the three below
    std::vector<char> committed_;    ///< per tile
    int next_border_ = 0;            ///< the next tile whose border is to be added
};

/// Most samples trace_wavefront() takes at once (it refills its batch's lanes from them as
/// paths end, and drains the batch at their end).
constexpr int WavefrontChunk = 64 * WavefrontBatch;

/// The samples of tiles (tx[i], ty[i]), i < count, in that order, traced by trace_wavefront()
/// in chunks of up to WavefrontChunk samples, which may span tiles; each chunk splatted in
/// the order the scalar loop splats (pixel by pixel, sample by sample) into its tile's block
/// (blocks[i]), so that every pixel sums the same values in the same order. Returns the
/// number of non-finite samples dropped.
uint64_t splat_tiles_wavefront(const RenderContext<RGB<float>> &ctx, const WavefrontScene &ws,
                               const Camera &camera, const IntegratorSettings &cfg,
                               const RenderRequest &req, const Tiles &tiles, const int *tx, const int *ty,
                               int count, const Film &film, Film::Block *blocks) {
    constexpr int Chunk = WavefrontChunk;
    // The thread's buffers, named through references: the loops below naming the thread_locals
    // themselves called __tls_get_addr at every sample (a thread_local of a shared library).
    static thread_local std::vector<WavefrontSample> samples_of_thread(Chunk);
    static thread_local std::vector<Vec2> pos_of_thread(Chunk);
    static thread_local std::vector<RGB<float>> L_of_thread(Chunk);
    static thread_local std::vector<int> tile_of_thread(Chunk);
    std::vector<WavefrontSample> &samples = samples_of_thread;
    std::vector<Vec2> &pos = pos_of_thread;
    std::vector<RGB<float>> &L = L_of_thread;
    std::vector<int> &tile_of = tile_of_thread;  // (its index in the group)
    // A batch's filter weights (SplatWeights: in SIMD lanes).
    SplatWeights weights(camera.filter);
    static_assert(SplatWeights::Batch == WavefrontBatch);
    int n = 0;
    uint64_t dropped = 0;
    auto flush = [&] {
        trace_wavefront(ctx, ws, cfg, camera, samples.data(), n, pos.data(), L.data());
        for (int first = 0; first < n; first += WavefrontBatch) {
            const int m = std::min(WavefrontBatch, n - first);
            const WavefrontSample *batch = &samples[size_t(first)];
            const RGB<float> *value = &L[size_t(first)];
            for (int k = 0; k < m; ++k) weights.set(k, batch[k].px, batch[k].py, pos[size_t(first + k)]);
            weights.compute(m);
            // Each pixel's run of samples in one splat (its finite ones).
            int run[WavefrontBatch];
            for (int k = 0; k < m;) {
                const int px = batch[k].px, py = batch[k].py;
                Film::Block &block = blocks[tile_of[size_t(first + k)]];
                int r = 0;
                for (; k < m && batch[k].px == px && batch[k].py == py; ++k) {
                    if (sample_is_finite(value[k])) {
                        run[r++] = k;
                    } else {
                        ++dropped;
                    }
                }
                film.splat_run(block, px, py, weights, run, r, value);
            }
        }
        n = 0;
    };
    for (int i = 0; i < count; ++i) {
        for_each_pixel_of_tile(camera, tiles, sample_rows(camera, req), tx[i], ty[i],
                               [&](int px, int py, uint64_t key) {
            PixelSeed seed(req.seed, key);
            for (int s = 0; s < req.spp; ++s) {
                tile_of[size_t(n)] = i;
                samples[size_t(n++)] = {px, py, seed, s};
                if (n == Chunk) flush();
            }
        });
    }
    if (n > 0) flush();
    return dropped;
}

/// Trace `spp` samples in every pixel of the rows `req` asks for (and of the border rows whose
/// splats reach them) and splat them into `film`.
template <typename S>
void splat_samples(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
                   const RenderRequest &req, const Tiles &tiles, const WorkerPool &pool, Film &film) {
    std::optional<WavefrontScene> wavefront;
    if constexpr (std::is_same_v<S, RGB<float>>) wavefront = wavefront_scene(ctx, cfg, camera);
    std::atomic<uint64_t> rays{0}, nonfinite{0};
    bool traced = false;  // by the wavefront
    if constexpr (std::is_same_v<S, RGB<float>>) {
        if (wavefront) {
            // Tiles in groups of consecutive ones whose samples fill about a chunk, so that
            // trace_wavefront drains its batch (paths ending one by one, their lanes left
            // empty) once per chunk, not once per tile.
            const RowRange rows = sample_rows(camera, req);
            const int64_t per_tile = std::max<int64_t>(1, int64_t(tiles.size) * tiles.size * req.spp);
            const int64_t group = std::max<int64_t>(1, WavefrontChunk / per_tile);
            for_each_tile_group(tiles, rows, pool, group, [&](const int *tx, const int *ty, int count) {
                const uint64_t rays_before = rays_traced;
                std::vector<Film::Block> blocks;
                for (int i = 0; i < count; ++i) blocks.push_back(film.block(tx[i], ty[i]));
                nonfinite += splat_tiles_wavefront(ctx, *wavefront, camera, cfg, req, tiles, tx, ty, count, film,
                                                   blocks.data());
                for (int i = 0; i < count; ++i) film.commit(tx[i], ty[i], std::move(blocks[i]));
                rays += rays_traced - rays_before;
            });
            traced = true;
        }
    }
    if (!traced) for_each_tile(tiles, sample_rows(camera, req), pool, [&](int tx, int ty) {
        uint64_t rays_before = rays_traced, dropped = 0;
        Film::Block block = film.block(tx, ty);
        for_each_pixel_of_tile(camera, tiles, sample_rows(camera, req), tx, ty,
                               [&](int px, int py, uint64_t key) {
            PixelSeed seed(req.seed, key);
            for (int s = 0; s < req.spp; ++s) {
                Sampler sampler(camera.sampler, seed, uint64_t(s));
                Vec2 pos = camera.sample_position(px, py, sampler);
                S L = trace(ctx, camera, cfg, pos, sampler);
                // Drop a non-finite sample rather than poisoning its pixels, and count it.
                if (!sample_is_finite(L)) {
                    ++dropped;
                    continue;
                }
                film.splat(block, px, py, pos, &L);
            }
        });
        film.commit(tx, ty, std::move(block));
        rays += rays_traced - rays_before;
        nonfinite += dropped;
    });
    assert(film.complete());
    if (req.rays) *req.rays = rays;
    if (req.nonfinite) *req.nonfinite = nonfinite;
}

/// a / b, or 0 where no sample reached the pixel. As Mitsuba's film, any nonzero weight sum
/// divides, also a negative one (filters with negative lobes).
double safe_div(double a, double b) { return b != 0.0 ? a / b : 0.0; }

}  // namespace

template <typename S>
void render_fwd(const RenderContext<S> &ctx, const Camera &camera, const IntegratorSettings &cfg,
                const RenderRequest &req, real_t<S> *out, const WorkerPool &pool) {
    Tiles tiles = tiles_of(camera);
    Film film(camera, tiles, requested_rows(camera, req));
    splat_samples(ctx, camera, cfg, req, tiles, pool, film);
    for (size_t i = 0; i < film.size(); ++i)
        for (int c = 0; c < 3; ++c) out[3 * i + c] = real_t<S>(safe_div(film[i].value[c], film[i].weight));
}

template <typename T>
void render_jvp(const RenderContext<Dual<T>> &ctx, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, T *out, T *out_tangent,
                const WorkerPool &pool) {
    Tiles tiles = tiles_of(camera);
    Film film(camera, tiles, requested_rows(camera, req), /*tangents=*/true);
    splat_samples(ctx, camera, cfg, req, tiles, pool, film);
    for (size_t i = 0; i < film.size(); ++i) {
        for (int c = 0; c < 3; ++c) {
            out[3 * i + c] = T(safe_div(film[i].value[c], film[i].weight));
            out_tangent[3 * i + c] = T(safe_div(film.tangent(i)[c], film[i].weight));
        }
    }
}

namespace {

/// Whether a material input may read a parameter marked in `watched`.
bool reads_watched(const Scene &scene, const TextureRef &r, const std::vector<char> &watched) {
    auto marked = [&](int p) { return p >= 0 && watched[size_t(p)] != 0; };
    if (r.attribute >= 0) {
        for (const Shape &shape : scene.geometry.shapes)
            if (marked(shape.attribute_param[0]) || marked(shape.attribute_param[1])) return true;
        return false;
    }
    if (r.texture >= 0) {
        const Texture &t = scene.textures[size_t(r.texture)];
        if (t.type == TextureType::Checkerboard) return marked(t.checkerboard.color0) || marked(t.checkerboard.color1);
        return marked(t.bitmap.param);
    }
    return marked(r.param);
}

}  // namespace

template <typename T>
void render_bwd(const Scene &scene, const Params<RGB<T>> &values, const Camera &camera,
                const IntegratorSettings &cfg, const RenderRequest &req, const T *adjoint,
                const std::vector<T *> &grads, const WorkerPool &pool) {
    // The image is sum_s w_p(x_s) L_s / W_p with W_p = sum_s w_p(x_s), so the adjoint of
    // sample s is sum_p w_p(x_s) adjoint_p / W_p: a gather with the splat's weights. W_p is
    // the weight sum of the backward pass's own samples (their positions cost no tracing).
    RowRange all{0, camera.crop_height};
    Tiles tiles = tiles_of(camera);
    Film weights(camera, tiles, all);
    // The pixels whose samples reach a pixel of nonzero adjoint (within the filter's border of
    // one), and the tiles that hold one: the others' samples gather zero adjoints and trace
    // nothing, and no such pixel's weight sum W_p holds their weights, so they are skipped
    // (a sparse adjoint, as a one-hot one per pixel of a gradient image, then costs the
    // pixels around it, not the image's every sample).
    const int width = camera.crop_width, height = camera.crop_height, border = camera.filter.border();
    std::vector<char> nonzero(size_t(width) * size_t(height), 0), across(nonzero.size(), 0), reaches(nonzero.size(), 0);
    for (size_t i = 0; i < nonzero.size(); ++i)
        nonzero[i] = adjoint[3 * i] != T(0) || adjoint[3 * i + 1] != T(0) || adjoint[3 * i + 2] != T(0);
    for (int y = 0; y < height; ++y)
        for (int x = 0; x < width; ++x)
            for (int i = std::max(0, x - border); i <= std::min(width - 1, x + border); ++i)
                across[size_t(y) * size_t(width) + size_t(x)] |= nonzero[size_t(y) * size_t(width) + size_t(i)];
    for (int y = 0; y < height; ++y)
        for (int x = 0; x < width; ++x)
            for (int j = std::max(0, y - border); j <= std::min(height - 1, y + border); ++j)
                reaches[size_t(y) * size_t(width) + size_t(x)] |= across[size_t(j) * size_t(width) + size_t(x)];
    auto reaching_pixel = [&](int px, int py) {  // (film coordinates, as for_each_pixel_of_tile's)
        return reaches[size_t(py - camera.crop_y) * size_t(width) + size_t(px - camera.crop_x)] != 0;
    };
    std::vector<char> reaching(size_t(tiles.nx) * size_t(tiles.ny), 0);
    for (int y = 0; y < height; ++y)
        for (int x = 0; x < width; ++x)
            reaching[size_t(tiles.index(x / tiles.size, y / tiles.size))] |= reaches[size_t(y) * size_t(width) + size_t(x)];
    const bool independent = camera.sampler.type == SamplerType::Independent;
    // (The independent sampler's positions a chunk at a time, and their filter weights.)
    constexpr int Chunk = SplatWeights::Batch;
    for_each_tile(tiles, all, pool, [&](int tx, int ty) {
        Film::Block block = weights.block(tx, ty);
        if (!reaching[size_t(tiles.index(tx, ty))]) return weights.commit(tx, ty, std::move(block));
        uint64_t stream[Chunk], index[Chunk];
        float u0[Chunk], u1[Chunk];
        SplatWeights chunk(camera.filter);
        for_each_pixel_of_tile(camera, tiles, all, tx, ty, [&](int px, int py, uint64_t key) {
            if (!reaching_pixel(px, py)) return;
            PixelSeed seed(req.seed, key);
            for (int s0 = 0; independent && s0 < req.spp; s0 += Chunk) {
                int n = std::min(Chunk, req.spp - s0);
                for (int k = 0; k < n; ++k) stream[k] = seed.stream, index[k] = uint64_t(s0 + k);
                independent_first_2d(n, stream, index, u0, u1);
                for (int k = 0; k < n; ++k) chunk.set(k, px, py, Vec2{float(px) + u0[k], float(py) + u1[k]});
                chunk.compute(n);
                weights.splat_weights(block, px, py, chunk, n);
            }
            for (int s = 0; !independent && s < req.spp; ++s) {
                Sampler sampler(camera.sampler, seed, uint64_t(s));
                weights.splat<RGB<T>>(block, px, py, camera.sample_position(px, py, sampler), nullptr);
            }
        });
        weights.commit(tx, ty, std::move(block));
    });
    assert(weights.complete());
    size_t n_pixels = weights.size();
    std::vector<RGB<double>> scaled(n_pixels);  // adjoint_p / W_p
    for (size_t i = 0; i < n_pixels; ++i)
        for (int c = 0; c < 3; ++c) scaled[i][c] = safe_div(double(adjoint[3 * i + c]), weights[i].weight);
    // (The sample at pos, or sample k of a batch of weights.)
    auto gather = [&](int px, int py, auto &&...sample) {
        RGB<double> dL;
        weights.for_each_reached(px, py, sample..., [&](size_t i, double w) { dL += scaled[i] * w; });
        return RGB<T>(T(dL[0]), T(dL[1]), T(dL[2]));
    };

    // One double gradient buffer per worker, covering the differentiated parameters.
    size_t n_params = values.data.size();
    std::vector<size_t> offset(n_params, 0);
    size_t total = 0;
    for (size_t p = 0; p < n_params; ++p) {
        offset[p] = total;
        if (grads[p]) total += size_t(values.numel[p]);
    }
    int n_workers = std::max(1, pool.workers);
    int n_tiles = tiles.nx * tiles.ny;
    std::vector<std::vector<double>> buffers(n_workers);
    // The backward pass in lanes (WavefrontVertex) for float renders in the wavefront's scenes
    // when no differentiated parameter is a roughness other than a rough conductor's (GGX or
    // Beckmann) or a roughplastic's (the lanes whose roughness derivatives WavefrontVertex
    // takes), or an input of a BSDF whose lane is not linear in its inputs other than a
    // roughplastic's diffuse reflectance (a Term record).
    std::optional<WavefrontScene> wavefront;
    std::vector<char> watched(n_params, 0);
    // The values the lanes read: a differentiated radiance's zero channels taken as 1
    // (WavefrontRecord::unit_radiance; the wavefront's emitter samples would skip an emitter
    // of zero radiance, and a zero channel's quotient C / Le fails).
    Params<RGB<T>> lane_values = values;
    std::vector<std::array<float, 3>> unit_radiance_values(n_params);
    std::vector<uint8_t> unit_radiance(n_params, 0);
    if constexpr (std::is_same_v<T, float>) {
        for (size_t p = 0; p < n_params; ++p) watched[p] = grads[p] != nullptr;
        for (const Emitter &e : scene.emitters) {
            const size_t p = size_t(e.radiance);
            if (e.radiance < 0 || !watched[p] || unit_radiance[p] || values.numel[p] > 3) continue;
            std::array<float, 3> &v = unit_radiance_values[p];
            for (int64_t c = 0; c < values.numel[p]; ++c) v[size_t(c)] = values.data[p][c];
            for (int64_t c = 0; c < values.numel[p]; ++c) {
                if (v[size_t(c)] != 0.f) continue;
                v[size_t(c)] = 1.f;
                unit_radiance[p] |= uint8_t(values.numel[p] == 1 ? 7 : 1 << c);
            }
            if (unit_radiance[p]) lane_values.data[p] = v.data();
        }
        wavefront = wavefront_scene(RenderContext<RGB<float>>(scene, lane_values), cfg, camera);
        // (Other lanes' inputs are read at trace time too, but the tape would re-trace every
        // path that reaches them.)
        for (size_t i = 0; wavefront && i < scene.bsdfs.size(); ++i) {
            const BSDF &b = scene.bsdfs[i];
            const auto lane = WavefrontScene::Lane(wavefront->materials[i].lane);
            if (b.alpha >= 0 && watched[size_t(b.alpha)] && lane != WavefrontScene::RoughMirror &&
                lane != WavefrontScene::RoughPlastic) {
                wavefront.reset();
                break;
            }
            if (linear_in_inputs(lane)) continue;
            // (A roughplastic's diffuse reflectance: a Term record.)
            const TextureRef *const reflectance = lane == WavefrontScene::RoughPlastic ? nullptr : &b.reflectance;
            for (const TextureRef *r : {reflectance, &b.specular_reflectance, &b.specular_transmittance})
                if (r && reads_watched(scene, *r, watched)) wavefront.reset();
        }
        if (wavefront) exclude_watched_inputs(*wavefront, scene, watched.data());
    }
    std::atomic<int> next_worker{0};
    std::atomic<uint64_t> rays{0}, nonfinite{0}, lane_paths{0}, tape_paths{0};
    pool.run([&] {
        int w = next_worker++;
        if (w >= n_workers) return;
        uint64_t rays_before = rays_traced, dropped = 0;
        std::vector<double> &buffer = buffers[w];
        buffer.assign(total, 0.0);
        Params<Var<T>> params;
        params.data = values.data;
        params.numel = values.numel;
        params.grad.assign(n_params, nullptr);
        for (size_t p = 0; p < n_params; ++p)
            if (grads[p]) params.grad[p] = buffer.data() + offset[p];
        RenderContext<Var<T>> ctx(scene, params);
        // Re-trace a sample's path with the tape, recording only what depends on
        // differentiated parameters, then push its adjoint back along it.
        auto tape_sample = [&](Sampler &sampler, Vec2 pos, const RGB<T> &dL) {
            tape_reset<T>();
            ++tape_paths;
            Var<T> L = trace(ctx, camera, cfg, pos, sampler);
            if (SpectrumTraits<Var<T>>::is_finite(L)) {
                L.backward(dL);
            } else {
                ++dropped;
            }
        };
        // In lanes: batches of samples traced by the float wavefront, each vertex of a
        // differentiated reflectance or transmittance (linear_in_inputs) depositing
        // dL . (L - L_before) / rho into what it read, each emission of a differentiated
        // radiance dL . C / Le, each rough conductor's vertex of a differentiated roughness
        // and each roughplastic's of a differentiated roughness or diffuse reflectance, per
        // channel, dL . (C_e dlog f(wo_e) + (L - L_before - C_e) dlog f(wo_s)), each record's
        // L being its sub-path's with `direct`'s several samples; the tape re-traces the
        // paths that read those parameters otherwise, or where a dielectric's rho has a zero
        // channel (the quotient fails; the other inputs' zero channels are taken as 1 in the
        // throughput, and a radiance's in the lanes' values: see WavefrontVertex::unit).
        std::optional<RenderContext<RGB<float>>> lanes_ctx;
        ParamReadLog log;
        log.watched = watched.data();
        // (Up to 16 batches' worth of samples per call: trace_wavefront refills its lanes.)
        constexpr int Chunk = 16 * WavefrontBatch;
        std::vector<WavefrontSample> batch(Chunk);
        std::vector<RGB<T>> adjoints(Chunk);
        std::vector<Vec2> positions(Chunk);
        std::vector<RGB<float>> radiance(Chunk);
        WavefrontRecord record;
        std::vector<std::array<int, 6>> zeros(Chunk);
        std::vector<RGB<double>> fake, fake_total(Chunk);
        const bool sub_paths = path_settings(cfg) && path_settings(cfg)->sub_paths > 1;
        std::vector<int> sub_end, next_end(Chunk);
        int n_batch = 0;
        if constexpr (std::is_same_v<T, float>) {
            if (wavefront) {
                lanes_ctx.emplace(scene, lane_values);
                record.unit_radiance = unit_radiance;
                lanes_ctx->params.log = &log;
                // The roughplastic tables' derivatives, where its roughness is differentiated
                // (its Term records read them; a float lookup adds them times 0).
                for (size_t i = 0; i < scene.bsdfs.size(); ++i) lanes_ctx->bsdf_state[i].dtables = ctx.bsdf_state[i].dtables;
            }
        }
        auto flush = [&] {
            if constexpr (std::is_same_v<T, float>) {
                trace_wavefront(*lanes_ctx, *wavefront, cfg, camera, batch.data(), n_batch, positions.data(),
                                radiance.data(), &record);
                // Each sample's first two records per channel whose rho was taken as 1 there
                // (WavefrontVertex::unit, Input): zeros[k][2 c], zeros[k][2 c + 1], -1 for
                // none. And the terms of the emission records whose Le the lanes read as 1 in
                // a channel (unit, Emission), in the path's radiance but truly zero: their sum
                // before each record (fake[i]) and over the path (fake_total[k]).
                bool any_unit = false, any_fake = false;
                for (int k = 0; k < n_batch; ++k) zeros[size_t(k)].fill(-1);
                for (size_t i = 0; i < record.vertices.size(); ++i) {
                    const WavefrontVertex &v = record.vertices[i];
                    for (int c = 0; c < 3; ++c) {
                        if (v.seq < 0 || v.kind == WavefrontVertex::Roughness || v.kind == WavefrontVertex::Term ||
                            v.kind == WavefrontVertex::End || v.value[c] != 0.f)
                            continue;
                        if (!v.unit) {
                            record.tape[size_t(v.seq)] = 1;
                            continue;
                        }
                        if (v.kind == WavefrontVertex::Emission) {
                            any_fake = true;
                            continue;
                        }
                        // (The first and second such records of a sample bound each other's
                        // terms, which `direct`'s sub-paths would not: the tape.)
                        if (sub_paths) {
                            record.tape[size_t(v.seq)] = 1;
                            continue;
                        }
                        int &first = zeros[size_t(v.seq)][size_t(2 * c)], &second = zeros[size_t(v.seq)][size_t(2 * c + 1)];
                        if (first < 0) first = int(i);
                        else if (second < 0) second = int(i);
                        any_unit = true;
                    }
                }
                if (any_fake) {
                    for (int k = 0; k < n_batch; ++k) fake_total[size_t(k)] = RGB<double>();
                    if (fake.size() < record.vertices.size()) fake.resize(record.vertices.size());
                    for (size_t i = 0; i < record.vertices.size(); ++i) {
                        const WavefrontVertex &v = record.vertices[i];
                        if (v.seq < 0) continue;
                        fake[i] = fake_total[size_t(v.seq)];
                        if (v.kind != WavefrontVertex::Emission || !v.unit) continue;
                        for (int c = 0; c < 3; ++c)
                            if (v.value[c] == 0.f) fake_total[size_t(v.seq)][c] += double(v.gathered[c]);
                    }
                }
                for (int k = 0; k < n_batch; ++k) {
                    lane_paths += record.tape[size_t(k)] ? 0 : 1;
                    if (record.tape[size_t(k)]) {
                        Sampler sampler(camera.sampler, batch[k].seed, uint64_t(batch[k].s));
                        Vec2 pos = camera.sample_position(batch[k].px, batch[k].py, sampler);
                        tape_sample(sampler, pos, adjoints[k]);
                    } else if (!sample_is_finite(radiance[k])) {
                        ++dropped;
                        record.tape[size_t(k)] = 1;  // (no deposits)
                    }
                }
                // With `direct`'s sub-paths, each record's terms end where its sub-path ends: at
                // the sample's next End record (sub_end[i]), or at its radiance.
                if (sub_paths) {
                    sub_end.assign(record.vertices.size(), -1);
                    std::fill(next_end.begin(), next_end.begin() + n_batch, -1);
                    for (size_t i = record.vertices.size(); i-- > 0;) {
                        const WavefrontVertex &v = record.vertices[i];
                        if (v.seq < 0) continue;
                        if (v.kind == WavefrontVertex::End) next_end[size_t(v.seq)] = int(i);
                        else sub_end[i] = next_end[size_t(v.seq)];
                    }
                }
                // The deposits, with the zero channels' bookkeeping only where a record needs it
                // (Unit: a reflectance's, Fake: a radiance's).
                auto deposit = [&](auto unit, auto fake_terms) {
                    constexpr bool Unit = decltype(unit)::value, Fake = decltype(fake_terms)::value;
                    for (size_t i = 0; i < record.vertices.size(); ++i) {
                        const WavefrontVertex &v = record.vertices[i];
                        if (v.seq < 0 || v.kind == WavefrontVertex::End || record.tape[size_t(v.seq)]) continue;
                        const RGB<float> &L = radiance[v.seq];
                        const int sub_path_end = sub_paths ? sub_end[i] : -1;
                        const RGB<T> &dL = adjoints[v.seq];
                        double g[3];
                        for (int c = 0; c < 3; ++c) {
                            // The path's true radiance before record j (an Input's or a Roughness's
                            // L_before), without the emission terms the lanes gathered with Le read
                            // as 1 where it is 0.
                            auto before = [&](size_t j) {
                                const double gathered = double(record.vertices[j].gathered[c]);
                                return Fake ? gathered - fake[j][c] : gathered;
                            };
                            // The path's radiance where this record's terms end: at its end, or in a
                            // channel whose rho was taken as 1 (WavefrontVertex::unit), at the first
                            // such record (the true radiance's end), and for that record at the
                            // second; a record after the first gathers nothing there.
                            double end = Fake ? double(L[c]) - fake_total[size_t(v.seq)][c] : double(L[c]);
                            if (sub_path_end >= 0) end = before(size_t(sub_path_end));
                            if constexpr (Unit) {
                                const std::array<int, 6> &z = zeros[size_t(v.seq)];
                                const int first = z[size_t(2 * c)], second = z[size_t(2 * c + 1)];
                                if (first >= 0 && int(i) > first) {
                                    g[c] = 0.0;
                                    continue;
                                }
                                if (first == int(i)) {
                                    end = second >= 0 ? before(size_t(second)) : end;
                                    g[c] = double(dL[c]) * (end - before(i));
                                    continue;
                                }
                                if (first >= 0) end = before(size_t(first));
                            }
                            if (v.kind == WavefrontVertex::Roughness || v.kind == WavefrontVertex::Term) {
                                // The emitter sample's C_e, then the rest.
                                double C = double(v.value[c]), rest = end - before(i) - C;
                                g[c] = double(dL[c]) * (C * double(v.dlog[0][c]) + rest * double(v.dlog[1][c]));
                                continue;
                            }
                            if (v.kind == WavefrontVertex::Input) {
                                g[c] = double(dL[c]) * (end - before(i)) / double(v.value[c]);
                                continue;
                            }
                            // Emission: C / Le, or where the lanes read Le as 1, C itself (dC/dLe).
                            const double Le = v.unit && v.value[c] == 0.f ? 1.0 : double(v.value[c]);
                            g[c] = double(dL[c]) * double(v.gathered[c]) / Le;
                        }
                        double *grad = params.grad[size_t(v.read.param)];
                        for (int i = 0; i < v.read.n; ++i) {
                            double w = double(v.read.weight[i]);
                            double *texel = grad + v.read.offset[i];
                            if (v.read.channels == 1) {
                                texel[0] += w * (g[0] + g[1] + g[2]);
                            } else {
                                for (int c = 0; c < 3; ++c) texel[c] += w * g[c];
                            }
                        }
                    }
                };
                if (any_fake) deposit(std::true_type{}, std::true_type{});
                else if (any_unit) deposit(std::true_type{}, std::false_type{});
                else deposit(std::false_type{}, std::false_type{});
            }
            n_batch = 0;
        };
        // Static, interleaved units of work, a unit being one sample index s in every pixel
        // of a tile: worker w always sums the same paths in the same order, so gradients are
        // bitwise reproducible for a given number of workers, and each tile's paths are
        // shared among the workers (whose loads stay even when some tiles cost more).
        // (The pixels' seeds are kept per tile: a worker's units run through a tile's samples.
        // With lanes the unit's positions are drawn first, in SIMD lanes.)
        int64_t n_units = int64_t(n_tiles) * req.spp;
        std::vector<PixelSeed> tile_seeds;
        std::vector<uint64_t> tile_streams, tile_index;
        std::vector<float> tile_u0, tile_u1;
        std::unique_ptr<SamplerColumns> tile_columns;
        SplatWeights tile_weights(camera.filter);
        int seeds_of = -1;
        for (int64_t unit = w; unit < n_units; unit += n_workers) {
            int tile = int(unit / req.spp), s = int(unit % req.spp);
            if (!reaching[size_t(tile)]) continue;
            if (tile != seeds_of) {
                tile_seeds.clear(), tile_streams.clear();
                for_each_pixel_of_tile(camera, tiles, all, tile % tiles.nx, tile / tiles.nx, [&](int, int, uint64_t key) {
                    tile_seeds.emplace_back(req.seed, key);
                    tile_streams.push_back(tile_seeds.back().stream);
                });
                tile_index.resize(tile_seeds.size()), tile_u0.resize(tile_seeds.size()), tile_u1.resize(tile_seeds.size());
                seeds_of = tile;
            }
            if (lanes_ctx && independent) {
                std::fill(tile_index.begin(), tile_index.end(), uint64_t(s));
                independent_first_2d(int(tile_seeds.size()), tile_streams.data(), tile_index.data(), tile_u0.data(),
                                     tile_u1.data());
            }
            // (The others' by SamplerColumns, Camera::sample_position's next_2d.)
            constexpr int C = SamplerColumns::Capacity;
            for (size_t first = 0; lanes_ctx && !independent && first < tile_seeds.size(); first += C) {
                const int m = int(std::min(tile_seeds.size() - first, size_t(C)));
                if (!tile_columns) tile_columns = std::make_unique<SamplerColumns>();
                for (int i = 0; i < m; ++i) {
                    tile_columns->seq[i] = tile_seeds[first + size_t(i)].sequence;
                    tile_columns->index[i] = uint32_t(s);
                }
                tile_columns->begin(camera.sampler, m, tile_streams.data() + first);
                tile_columns->next_2d(camera.sampler, m, nullptr, tile_u0.data() + first, tile_u1.data() + first);
            }
            // Their filter weights at once, where the tile's pixels fit a batch (they do but
            // under filters wider than 8 pixels, whose tiles are larger).
            const bool batched = lanes_ctx && tile_seeds.size() <= size_t(SplatWeights::Batch);
            if (batched) {
                size_t pixel = 0;
                for_each_pixel_of_tile(camera, tiles, all, tile % tiles.nx, tile / tiles.nx, [&](int px, int py, uint64_t) {
                    const size_t i = pixel++;
                    tile_weights.set(int(i), px, py, Vec2{float(px) + tile_u0[i], float(py) + tile_u1[i]});
                });
                tile_weights.compute(int(pixel));
            }
            size_t pixel = 0;
            for_each_pixel_of_tile(camera, tiles, all, tile % tiles.nx, tile / tiles.nx,
                                   [&](int px, int py, uint64_t) {
                const size_t i = pixel++;
                if (!reaching_pixel(px, py)) return;
                const PixelSeed &seed = tile_seeds[i];
                if (lanes_ctx) {
                    RGB<T> dL = batched ? gather(px, py, tile_weights, int(i))
                                        : gather(px, py, Vec2{float(px) + tile_u0[i], float(py) + tile_u1[i]});
                    if (dL[0] == T(0) && dL[1] == T(0) && dL[2] == T(0)) return;
                    batch[n_batch] = {px, py, seed, s};
                    adjoints[n_batch++] = dL;
                    if (n_batch == Chunk) flush();
                    return;
                }
                Sampler sampler(camera.sampler, seed, uint64_t(s));
                Vec2 pos = camera.sample_position(px, py, sampler);
                RGB<T> dL = gather(px, py, pos);
                if (dL[0] == T(0) && dL[1] == T(0) && dL[2] == T(0)) return;
                tape_sample(sampler, pos, dL);
            });
        }
        if (n_batch > 0) flush();
        tape_reset<T>();
        rays += rays_traced - rays_before;
        nonfinite += dropped;
    });
    // Reduce the workers' buffers in worker order.
    for (size_t p = 0; p < n_params; ++p) {
        if (!grads[p]) continue;
        for (int64_t k = 0; k < values.numel[p]; ++k) {
            double g = double(grads[p][k]);
            for (int w = 0; w < n_workers; ++w)
                if (!buffers[w].empty()) g += buffers[w][offset[p] + size_t(k)];
            grads[p][k] = T(g);
        }
    }
    if (req.rays) *req.rays = rays;
    if (req.nonfinite) *req.nonfinite = nonfinite;
    if (req.lane_paths) *req.lane_paths = lane_paths;
    if (req.tape_paths) *req.tape_paths = tape_paths;
}

template void render_fwd<RGB<float>>(const RenderContext<RGB<float>> &, const Camera &,
                                     const IntegratorSettings &, const RenderRequest &, float *,
                                     const WorkerPool &);
template void render_fwd<RGB<double>>(const RenderContext<RGB<double>> &, const Camera &,
                                      const IntegratorSettings &, const RenderRequest &, double *,
                                      const WorkerPool &);
template void render_bwd<float>(const Scene &, const Params<RGB<float>> &, const Camera &,
                                const IntegratorSettings &, const RenderRequest &, const float *,
                                const std::vector<float *> &, const WorkerPool &);
template void render_bwd<double>(const Scene &, const Params<RGB<double>> &, const Camera &,
                                 const IntegratorSettings &, const RenderRequest &,
                                 const double *, const std::vector<double *> &,
                                 const WorkerPool &);
template void render_jvp<float>(const RenderContext<Dual<float>> &, const Camera &,
                                const IntegratorSettings &, const RenderRequest &, float *,
                                float *, const WorkerPool &);
template void render_jvp<double>(const RenderContext<Dual<double>> &, const Camera &,
                                 const IntegratorSettings &, const RenderRequest &, double *,
                                 double *, const WorkerPool &);

}  // namespace rbpt
