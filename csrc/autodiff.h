// Reverse-mode automatic differentiation: Var<T>, the report's recorded "Vector" (TR-21-05,
// sections 3.1 and 3.3), an RGB value of T = float or double that the path tracer can run on.
//
// Design:
// - Tape: one thread_local arena per T (Tape<T>::local()). Nodes live in a std::vector that
//   grows once and is truncated by rewind()/reset() without giving back its capacity, so
//   recording allocates nothing after warm-up. No shared_ptr, no std::function.
// - Node layout: {parent a, parent b, kind, RGB partial da, RGB partial db}. Every operation
//   is componentwise, so a partial is diagonal: one RGB per parent. A leaf (a variable) keeps
//   its accumulated gradient in da. A custom node refers to a functor placement-new'ed in a
//   block arena that never moves, called through a function-pointer thunk; non-trivial
//   destructors run when the tape is rewound past the node.
// - Constant propagation: a Var whose node is -1 is a constant. An operation whose operands
//   are all constants, or that runs under NoRecord, returns a constant and records nothing;
//   constants never appear as parents. Scalars are Vars with equal channels, so
//   real_t<Var<T>> = Var<T> serves both spectra and parameters such as roughness.
// - backward(): one iterative reverse sweep over tape indices [floor, root] (no recursion, so
//   long chains are fine). A custom functor runs with the floor raised to the tape's end:
//   whatever it records and back-propagates is swept locally, while contributions to older
//   nodes stay in the enclosing sweep's adjoints for that sweep to carry on. Its nodes are
//   discarded when it returns. This is how integrate() runs a fresh forward and backward pass
//   inside the outer backward pass without disturbing it.
// - Sink nodes: a value read from a caller's parameter (a constant, or a few texels) whose
//   adjoint the sweep scatters straight into the caller's double gradient buffer
//   (GradientSink). It is what a custom node could do, without the functor's arena, thunk
//   and bookkeeping: the backward pass reads two parameters per path vertex.
// - A Var belongs to the thread that recorded it and is valid until the tape is rewound past
//   its node (e.g. tape_reset()); constants stay valid forever.
#pragma once

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#include "math.h"

namespace rbpt {

template <typename T>
class Var;

namespace detail {

/// What the hot path reads of its thread: whether operations on variables are recorded
/// (cleared by NoRecord) and the thread's tapes (Tape<float>, Tape<double>), created at first
/// use. One trivially destructible thread_local, so that an operation costs one TLS address
/// lookup (a call in a shared library) and no initialisation guard.
struct ThreadState {
    bool recording = true;
    void *tapes[2] = {nullptr, nullptr};
};
inline thread_local ThreadState thread_state;

template <typename T>
inline bool all_zero(const RGB<T> &a) {
    return a.v[0] == T(0) && a.v[1] == T(0) && a.v[2] == T(0);
}

/// Componentwise f(a).
template <typename T, typename F>
inline RGB<T> map(const RGB<T> &a, F f) {
    return {f(a.v[0]), f(a.v[1]), f(a.v[2])};
}

/// Bump allocator over blocks that never move, so that functors of any type can live in it.
/// rewind() returns to an earlier position; blocks are kept for reuse.
class Arena {
public:
    struct Position {
        size_t block = 0, offset = 0;
    };
    static constexpr size_t BlockSize = 64 * 1024;

    void *allocate(size_t size, size_t align) {
        for (;; ++pos_.block, pos_.offset = 0) {
            if (pos_.block == blocks_.size()) {
                size_t n = std::max(BlockSize, size + align);
                blocks_.push_back({std::unique_ptr<std::byte[]>(new std::byte[n]), n});
            }
            const Block &b = blocks_[pos_.block];
            uintptr_t base = reinterpret_cast<uintptr_t>(b.data.get());
            uintptr_t p = (base + pos_.offset + align - 1) & ~uintptr_t(align - 1);
            if (p + size <= base + b.size) {
                pos_.offset = p + size - base;
                return reinterpret_cast<void *>(p);
            }
        }
    }
    Position mark() const { return pos_; }
    void rewind(Position p) { pos_ = p; }
    /// Bytes held by the arena (constant once warmed up).
    size_t capacity() const {
        size_t n = 0;
        for (const Block &b : blocks_) n += b.size;
        return n;
    }

private:
    struct Block {
        std::unique_ptr<std::byte[]> data;
        size_t size;
    };
    std::vector<Block> blocks_;
    Position pos_;
};

}  // namespace detail

/// Where the adjoint of a sink node goes: up to four entries of a caller-owned double buffer,
/// each weighted; an entry of one channel receives the sum of the adjoint's three channels,
/// an entry of three channels the adjoint itself.
struct GradientSink {
    double *grad;
    int64_t offset[4];  ///< of each entry's first channel in `grad`
    float weight[4];
    int n;         ///< entries (1 to 4)
    int channels;  ///< 1 or 3

    /// Add weight[k] * adjoint into the entries.
    template <typename T>
    void scatter(const RGB<T> &d) const {
        for (int k = 0; k < n; ++k) {
            double w = double(weight[k]);
            double *entry = grad + offset[k];
            if (channels == 1) {
                entry[0] += w * (double(d[0]) + double(d[1]) + double(d[2]));
            } else {
                for (int c = 0; c < 3; ++c) entry[c] += w * double(d[c]);
            }
        }
    }
};

/// RAII guard: while alive, operations on this thread record nothing and return constants
/// (also the custom-functor constructor). Variables can still be created.
class NoRecord {
public:
    NoRecord() : saved_(detail::thread_state.recording) { detail::thread_state.recording = false; }
    ~NoRecord() { detail::thread_state.recording = saved_; }
    NoRecord(const NoRecord &) = delete;
    NoRecord &operator=(const NoRecord &) = delete;

private:
    bool saved_;
};

/// The thread-local record of operations on Var<T>, with the reverse sweep.
template <typename T>
class Tape {
public:
    /// The calling thread's tape.
    static Tape &local() {
        void *&slot = detail::thread_state.tapes[std::is_same_v<T, double>];
        if (__builtin_expect(slot == nullptr, 0)) slot = create();
        return *static_cast<Tape *>(slot);
    }

    Tape() = default;
    Tape(const Tape &) = delete;
    Tape &operator=(const Tape &) = delete;
    ~Tape() { rewind(0); }

    /// Number of recorded nodes: a position to rewind() to later.
    size_t size() const { return nodes_.size(); }
    /// Discard the nodes recorded since `position` (destroying their functors); Vars recorded
    /// since then become invalid. Capacity is kept.
    void rewind(size_t position) {
        assert(position >= size_t(floor_) && position <= nodes_.size());
        while (!customs_.empty() && size_t(customs_.back().node) >= position) {
            const Custom &c = customs_.back();
            if (c.destroy) c.destroy(c.payload);
            arena_.rewind(c.arena_mark);
            customs_.pop_back();
        }
        while (!sinks_.empty() && size_t(sinks_.back().node) >= position) sinks_.pop_back();
        nodes_.erase(nodes_.begin() + std::ptrdiff_t(position), nodes_.end());
    }
    /// Discard everything (all Vars of this thread but constants become invalid); inside a
    /// custom functor, everything the functor recorded.
    void reset() { rewind(size_t(floor_)); }

    /// Nodes the tape can hold without reallocating.
    size_t node_capacity() const { return nodes_.capacity(); }
    /// Bytes reserved for custom functors.
    size_t arena_capacity() const { return arena_.capacity(); }

private:
    friend class Var<T>;
    enum class Kind : int32_t { Op, Leaf, Custom, Sink };

    /// A recorded operation: d(result) = da d(a) + db d(b), componentwise.
    struct Node {
        int32_t a, b;  ///< parents (-1: none); a Custom (Sink) node keeps its functor's (sink's) index in a
        Kind kind;
        RGB<T> da, db;  ///< partials; a Leaf accumulates its gradient in da
        Node(int32_t a, int32_t b, Kind kind, const RGB<T> &da, const RGB<T> &db)
            : a(a), b(b), kind(kind), da(da), db(db) {}
    };

    /// A custom backward functor living in the arena.
    struct Custom {
        void (*call)(void *payload, const RGB<T> &grad);
        void (*destroy)(void *payload);  ///< nullptr when trivially destructible
        void *payload;
        detail::Arena::Position arena_mark;  ///< arena position before the payload
        int32_t node;
    };

    /// A sink node's destination.
    struct Sink {
        GradientSink to;
        int32_t node;
    };

    /// The calling thread's tape, owned by a thread_local that destroys it at the thread's
    /// exit (and clears the slot, so that a later use creates a new one).
    [[gnu::noinline]] static Tape *create() {
        static_assert(std::is_same_v<T, float> || std::is_same_v<T, double>);
        struct Owner {
            std::unique_ptr<Tape> tape;
            ~Owner() {
                tape.reset();
                detail::thread_state.tapes[std::is_same_v<T, double>] = nullptr;
            }
        };
        static thread_local Owner owner;
        if (!owner.tape) owner.tape.reset(new Tape());
        return owner.tape.get();
    }

    template <typename F>
    static void call_thunk(void *p, const RGB<T> &grad) {
        (*static_cast<F *>(p))(grad);
    }
    template <typename F>
    static void destroy_thunk(void *p) {
        static_cast<F *>(p)->~F();
    }

    int32_t push(int32_t a, int32_t b, Kind kind, const RGB<T> &da, const RGB<T> &db) {
        assert(nodes_.size() < size_t(INT32_MAX));
        nodes_.emplace_back(a, b, kind, da, db);  // built in place
        return int32_t(nodes_.size() - 1);
    }
    int32_t push_op(int32_t a, const RGB<T> &da, int32_t b, const RGB<T> &db) {
        if (a < 0) return push(b, -1, Kind::Op, db, RGB<T>());
        return push(a, b, Kind::Op, da, db);
    }
    int32_t push_leaf() { return push(-1, -1, Kind::Leaf, RGB<T>(), RGB<T>()); }
    /// (Filled in place: a GradientSink assembled on the stack and copied whole made the
    /// copy's wide load wait for the narrow stores that wrote it.)
    int32_t push_sink(double *grad, int channels, int n, const int64_t *offset, const float *weight) {
        Sink &s = sinks_.emplace_back();
        s.node = int32_t(nodes_.size());
        s.to.grad = grad;
        s.to.channels = channels;
        s.to.n = n;
        for (int k = 0; k < n; ++k) {
            s.to.offset[k] = offset ? offset[k] : 0;
            s.to.weight[k] = weight ? weight[k] : 1.f;
        }
        return push(int32_t(sinks_.size() - 1), -1, Kind::Sink, RGB<T>(), RGB<T>());
    }
    template <typename F>
    int32_t push_custom(F &&f) {
        using Fn = std::decay_t<F>;
        detail::Arena::Position mark = arena_.mark();
        void *p = arena_.allocate(sizeof(Fn), alignof(Fn));
        new (p) Fn(std::forward<F>(f));
        int32_t node = int32_t(nodes_.size());
        customs_.push_back({&call_thunk<Fn>,
                            std::is_trivially_destructible_v<Fn> ? nullptr : &destroy_thunk<Fn>, p,
                            mark, node});
        return push(int32_t(customs_.size() - 1), -1, Kind::Custom, RGB<T>(), RGB<T>());
    }

    /// Reverse sweep from `root` seeded with `seed`, over the nodes at or above the floor.
    /// Below the floor (inside a custom functor), the seed is left for the enclosing sweep.
    void backward(int32_t root, const RGB<T> &seed) {
        if (adjoint_.size() < nodes_.size()) adjoint_.resize(nodes_.size());
        if (root < floor_) {
            adjoint_[root] += seed;
            return;
        }
        std::fill(adjoint_.begin() + floor_, adjoint_.begin() + root + 1, RGB<T>());
        adjoint_[root] = seed;
        for (int32_t i = root; i >= floor_; --i) {
            RGB<T> g = adjoint_[i];
            if (detail::all_zero(g)) continue;
            Node &n = nodes_[i];
            switch (n.kind) {
                case Kind::Op:
                    adjoint_[n.a] += n.da * g;
                    if (n.b >= 0) adjoint_[n.b] += n.db * g;
                    break;
                case Kind::Leaf: n.da += g; break;
                case Kind::Custom: run_custom(n.a, g); break;  // may reallocate nodes_
                case Kind::Sink: sinks_[n.a].to.scatter(g); break;
            }
        }
    }

    /// Call a custom functor on a scope of its own: recording on, floor at the tape's end,
    /// and whatever it recorded discarded afterwards.
    void run_custom(int32_t index, RGB<T> grad) {
        struct Scope {
            Tape &tape;
            size_t mark;
            int32_t floor;
            bool recording;
            ~Scope() {
                tape.rewind(mark);
                tape.floor_ = floor;
                detail::thread_state.recording = recording;
            }
        } scope{*this, nodes_.size(), floor_, detail::thread_state.recording};
        const Custom c = customs_[index];  // a copy: customs_ may grow during the call
        floor_ = int32_t(nodes_.size());
        detail::thread_state.recording = true;
        c.call(c.payload, grad);
    }

    RGB<T> &leaf_grad(int32_t node) {
        assert(node >= 0 && size_t(node) < nodes_.size() && nodes_[node].kind == Kind::Leaf);
        return nodes_[node].da;
    }
    bool is_leaf(int32_t node) const {
        assert(node >= 0 && size_t(node) < nodes_.size());
        return nodes_[node].kind == Kind::Leaf;
    }

    std::vector<Node> nodes_;
    std::vector<RGB<T>> adjoint_;  ///< scratch of the reverse sweep, parallel to nodes_
    std::vector<Custom> customs_;
    std::vector<Sink> sinks_;
    detail::Arena arena_;
    int32_t floor_ = 0;  ///< lowest node the current sweep may visit
};

/// Clear the calling thread's tape of Var<T> (keeping its capacity).
template <typename T>
inline void tape_reset() {
    Tape<T>::local().reset();
}

/// Reverse-mode RGB number. A *variable* (`Var x(RGB{1, 2, 3}, true)`) has an accumulated
/// gradient; an expression involving a variable is recorded; an expression of *constants*
/// (`Var c(RGB{4, 5, 6})`, `Var(0.5)`) is a constant and records nothing.
template <typename T>
class Var {
public:
    using Scalar = T;

    /// The constant 0.
    Var() = default;
    /// A constant scalar broadcast to RGB (implicit, so that `x * 0.5f`, `1.f - x` work).
    template <typename U, std::enable_if_t<std::is_arithmetic_v<U> && !std::is_same_v<U, bool>,
                                           int> = 0>
    Var(U s) : value_(T(s)) {}  // NOLINT: implicit by design
    /// A constant RGB value.
    Var(const RGB<T> &value) : value_(value) {}  // NOLINT: implicit by design
    /// A constant RGB value, from its channels (`Var c = {4, 5, 6}`).
    Var(T r, T g, T b) : value_(r, g, b) {}
    /// A variable (recorded even under NoRecord) if `requires_grad`, else a constant.
    Var(const RGB<T> &value, bool requires_grad) : value_(value) {
        if (requires_grad) node_ = Tape<T>::local().push_leaf();
    }
    /// A node with the value of `value` whose backward step is `backward(grad)`, called with
    /// the gradient reaching the node (const RGB<T>&). Only the value is taken: the functor
    /// *replaces* the derivative of `value`'s graph (as the report's integrate operator needs);
    /// to chain into it as well, call `value.backward(grad)` from the functor. The functor is
    /// moved into the tape's arena (any size, no per-node heap allocation after warm-up) and
    /// destroyed when the tape is rewound past the node. It may record and back-propagate
    /// through new nodes (discarded when it returns) and may propagate to Vars created before
    /// this node only. Under NoRecord the result is a constant and the functor is dropped.
    template <typename F,
              std::enable_if_t<std::is_invocable_v<std::decay_t<F> &, const RGB<T> &>, int> = 0>
    Var(const Var &value, F &&backward) : value_(value.value_) {
        if (detail::thread_state.recording) node_ = Tape<T>::local().push_custom(std::forward<F>(backward));
    }

    /// A node with value `value` whose backward step scatters the gradient reaching it into
    /// `grad` (which must outlive the sweep), as a GradientSink of `n` entries: at offset[k]
    /// with weight[k] (nullptr: the one entry at 0, weight 1). Under NoRecord, a constant.
    Var(const RGB<T> &value, double *grad, int channels, int n = 1, const int64_t *offset = nullptr,
        const float *weight = nullptr)
        : value_(value) {
        if (detail::thread_state.recording)
            node_ = Tape<T>::local().push_sink(grad, channels, n, offset, weight);
    }

    /// The value.
    const RGB<T> &value() const { return value_; }
    /// Whether this is a variable or depends on one (i.e. has a node on the tape).
    bool requires_grad() const { return node_ >= 0; }
    /// Index of the node on the tape, -1 for a constant.
    int32_t node() const { return node_; }
    /// The gradient accumulated by backward() into a variable; zero for anything else.
    RGB<T> grad() const {
        Tape<T> &tape = Tape<T>::local();
        return node_ >= 0 && tape.is_leaf(node_) ? tape.leaf_grad(node_) : RGB<T>();
    }
    /// Reset a variable's accumulated gradient to zero.
    void zero_grad() {
        Tape<T> &tape = Tape<T>::local();
        if (node_ >= 0 && tape.is_leaf(node_)) tape.leaf_grad(node_) = RGB<T>();
    }
    /// Propagate `seed` (d loss / d this) to every variable this depends on, accumulating
    /// into their gradients. A no-op on a constant.
    void backward(const RGB<T> &seed = RGB<T>(T(1))) const {
        if (node_ >= 0) Tape<T>::local().backward(node_, seed);
    }
    /// A constant with the same value. (The free detach() of math.h gives a Color3f.)
    Var detach() const { return Var(value_); }

    /// Result of a componentwise function of `a`: value `value`, derivative `partial()`
    /// (called only when the result is recorded).
    template <typename P>
    [[gnu::always_inline]] static Var unary(const RGB<T> &value, const Var &a, P partial) {
        Var r(value);
        if (__builtin_expect(a.node_ >= 0, 0) && detail::thread_state.recording)
            r.node_ = Tape<T>::local().push_op(a.node_, partial(), -1, RGB<T>());
        return r;
    }
    /// Result of a componentwise function of `a` and `b`: value `value`, partial derivatives
    /// `partial_a()` and `partial_b()` (called only for recorded operands).
    template <typename PA, typename PB>
    [[gnu::always_inline]] static Var binary(const RGB<T> &value, const Var &a, const Var &b,
                                             PA partial_a, PB partial_b) {
        Var r(value);
        // (a.node_ & b.node_) >= 0: not both -1, i.e. at least one operand is recorded.
        if (__builtin_expect((a.node_ & b.node_) >= 0, 0) && detail::thread_state.recording) {
            r.node_ = Tape<T>::local().push_op(a.node_, a.node_ >= 0 ? partial_a() : RGB<T>(),
                                               b.node_, b.node_ >= 0 ? partial_b() : RGB<T>());
        }
        return r;
    }

    /// Componentwise arithmetic; scalars and RGB<T> operands convert to constants, so only
    /// operands that are recorded become parents.
    [[gnu::always_inline]] friend Var operator+(const Var &a, const Var &b) {
        return binary(a.value_ + b.value_, a, b, [] { return RGB<T>(T(1)); },
                      [] { return RGB<T>(T(1)); });
    }
    [[gnu::always_inline]] friend Var operator-(const Var &a, const Var &b) {
        return binary(a.value_ - b.value_, a, b, [] { return RGB<T>(T(1)); },
                      [] { return RGB<T>(T(-1)); });
    }
    [[gnu::always_inline]] friend Var operator*(const Var &a, const Var &b) {
        return binary(a.value_ * b.value_, a, b, [&] { return b.value_; },
                      [&] { return a.value_; });
    }
    [[gnu::always_inline]] friend Var operator/(const Var &a, const Var &b) {
        RGB<T> q = a.value_ / b.value_;
        return binary(q, a, b, [&] { return T(1) / b.value_; },
                      [&] { return T(-1) * q / b.value_; });
    }
    friend Var operator-(const Var &a) {
        return unary(T(-1) * a.value_, a, [] { return RGB<T>(T(-1)); });
    }
    /// Compound assignment: rebinds this Var to the new (recorded) result.
    Var &operator+=(const Var &b) { return *this = *this + b; }
    Var &operator-=(const Var &b) { return *this = *this - b; }
    Var &operator*=(const Var &b) { return *this = *this * b; }
    Var &operator/=(const Var &b) { return *this = *this / b; }

private:
    RGB<T> value_;
    int32_t node_ = -1;
};

/// Componentwise e^x.
template <typename T>
Var<T> exp(const Var<T> &x) {
    RGB<T> e = detail::map(x.value(), [](T v) { return std::exp(v); });
    return Var<T>::unary(e, x, [&] { return e; });
}
/// Componentwise natural logarithm.
template <typename T>
Var<T> log(const Var<T> &x) {
    return Var<T>::unary(detail::map(x.value(), [](T v) { return std::log(v); }), x,
                         [&] { return T(1) / x.value(); });
}
/// Componentwise square root (infinite derivative at 0).
template <typename T>
Var<T> sqrt(const Var<T> &x) {
    RGB<T> s = detail::map(x.value(), [](T v) { return std::sqrt(v); });
    return Var<T>::unary(s, x, [&] { return T(0.5) / s; });
}
/// Componentwise error function; d erf(x) = 2/sqrt(pi) e^(-x^2).
template <typename T>
Var<T> erf(const Var<T> &x) {
    return Var<T>::unary(detail::map(x.value(), [](T v) { return std::erf(v); }), x, [&] {
        return detail::map(x.value(), [](T v) {
            return T(1.1283791670955126) * std::exp(-v * v);
        });
    });
}
/// Componentwise x^p for a constant exponent p.
template <typename T>
Var<T> pow(const Var<T> &x, typename Var<T>::Scalar p) {
    return Var<T>::unary(detail::map(x.value(), [p](T v) { return std::pow(v, p); }), x, [&] {
        return detail::map(x.value(), [p](T v) { return p * std::pow(v, p - T(1)); });
    });
}
/// Componentwise |x| (derivative sign(x), 0 at 0).
template <typename T>
Var<T> abs(const Var<T> &x) {
    return Var<T>::unary(detail::map(x.value(), [](T v) { return std::abs(v); }), x, [&] {
        return detail::map(x.value(), [](T v) { return T((v > T(0)) - (v < T(0))); });
    });
}
/// Componentwise minimum; each channel's derivative goes to the operand selected (a on ties).
template <typename T>
Var<T> min(const Var<T> &a, const Var<T> &b) {
    const RGB<T> &x = a.value(), &y = b.value();
    RGB<T> sel = {T(x.v[0] <= y.v[0]), T(x.v[1] <= y.v[1]), T(x.v[2] <= y.v[2])};
    return Var<T>::binary(sel * x + (T(1) - sel) * y, a, b, [&] { return sel; },
                          [&] { return T(1) - sel; });
}
/// Componentwise maximum; each channel's derivative goes to the operand selected (a on ties).
template <typename T>
Var<T> max(const Var<T> &a, const Var<T> &b) {
    const RGB<T> &x = a.value(), &y = b.value();
    RGB<T> sel = {T(x.v[0] >= y.v[0]), T(x.v[1] >= y.v[1]), T(x.v[2] >= y.v[2])};
    return Var<T>::binary(sel * x + (T(1) - sel) * y, a, b, [&] { return sel; },
                          [&] { return T(1) - sel; });
}
/// min of a Var and a constant scalar (broadcast).
template <typename T>
Var<T> min(const Var<T> &a, typename Var<T>::Scalar b) {
    return min(a, Var<T>(b));
}
/// min of a constant scalar and a Var.
template <typename T>
Var<T> min(typename Var<T>::Scalar a, const Var<T> &b) {
    return min(Var<T>(a), b);
}
/// max of a Var and a constant scalar.
template <typename T>
Var<T> max(const Var<T> &a, typename Var<T>::Scalar b) {
    return max(a, Var<T>(b));
}
/// max of a constant scalar and a Var.
template <typename T>
Var<T> max(typename Var<T>::Scalar a, const Var<T> &b) {
    return max(Var<T>(a), b);
}
/// A constant with the value of x (generic spelling of x.detach()).
template <typename T>
Var<T> no_grad(const Var<T> &x) {
    return x.detach();
}

/// Traits for the path tracer: scalars are Vars; detach() gives the value as a Color3f.
template <typename T>
struct SpectrumTraits<Var<T>> {
    using Real = Var<T>;  ///< scalars are RGB with equal channels
    static Color3f detach(const Var<T> &s) { return SpectrumTraits<RGB<T>>::detach(s.value()); }
    static bool is_finite(const Var<T> &s) { return SpectrumTraits<RGB<T>>::is_finite(s.value()); }
    static bool has_derivative(const Var<T> &s) { return s.requires_grad(); }
};

/// Value of a scalar Var (its first channel), without derivatives.
template <typename T>
inline float detach_real(const Var<T> &x) {
    return float(x.value().v[0]);
}

namespace detail {

/// The sample of a sampler's {sample, pdf} record.
template <typename Record>
auto sample_of(Record r) {
    auto [sample, pdf] = r;
    (void)pdf;
    return sample;
}

/// Backward step of integrate(): a fresh Monte Carlo estimate of the adjoint, drawing new
/// samples from the sampler (which continues the stream the forward estimate used).
template <typename T, typename Forward, typename Sampler>
struct IntegrateBackward {
    Forward forward;
    Sampler sampler;
    size_t n_samples;

    void operator()(const RGB<T> &grad) {
        Tape<T> &tape = Tape<T>::local();
        for (size_t i = 0; i < n_samples; ++i) {
            auto [sample, pdf] = sampler();
            if (!(pdf > 0)) continue;
            size_t mark = tape.size();
            forward(sample).backward(grad * T(1.0 / (double(pdf) * double(n_samples))));
            tape.rewind(mark);
        }
    }
};

}  // namespace detail

/// The report's unbiased integration operator (section 3.3): the Monte Carlo estimate
/// (1/n) sum forward(x_i) / pdf_i over n samples {x_i, pdf_i} = sampler(), whose backward
/// step draws n *new* samples from the same (continued) sampler and back-propagates
/// grad / (pdf n) through forward at each, so value and gradient are independent estimates.
/// The forward estimate runs under NoRecord (it leaves one node on the tape, the result's).
/// `forward(sample)` must return a Var<T>; `sampler()` a pair-like {sample, pdf}, with
/// pdf <= 0 counted as a zero contribution. Both are copied into the tape with the node.
template <typename Forward, typename Sampler>
auto integrate(Forward forward, Sampler sampler, size_t n_samples) {
    using Sample = decltype(detail::sample_of(std::declval<std::invoke_result_t<Sampler &>>()));
    using V = std::decay_t<std::invoke_result_t<Forward &, Sample>>;
    using T = typename V::Scalar;
    static_assert(std::is_same_v<V, Var<T>>, "integrate: forward(sample) must return a Var");
    RGB<T> sum(T(0));
    {
        NoRecord no_record;
        for (size_t i = 0; i < n_samples; ++i) {
            auto [sample, pdf] = sampler();
            if (pdf > 0) sum += forward(sample).value() * T(1.0 / double(pdf));
        }
    }
    if (n_samples > 0) sum = sum * T(1.0 / double(n_samples));
    return Var<T>(sum, detail::IntegrateBackward<T, Forward, Sampler>{
                           std::move(forward), std::move(sampler), n_samples});
}

}  // namespace rbpt
