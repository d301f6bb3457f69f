// Kernel gradient of a stride-1 NHWC convolution on CPU, as an XLA FFI custom call
// (irdepth_jax/xla_cpu/native_conv.py builds this file with the machine's C++ compiler,
// -O3 -march=native, and registers it).
//
//   dw[p, q, c, d] = sum over b, i, j of x[b, i + p - top, j + q - left, c] * g[b, i, j, d]
//
// x (B, H, W, C), g (B, OH, OW, D), dw (KH, KW, C, D), float32; x is zero outside its
// bounds (the convolution's padding). Register tiles of R input channels x 2 vectors of output
// channels accumulate one output row of g at a time: per pixel, two vector loads of g and R
// broadcasts of x feed 2 R fused multiply-adds, no im2col copy. The tiles are split among the
// XLA CPU client's intra-op threads; every element of dw is summed by one thread in a fixed
// order, so results do not depend on the scheduling.

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

#if defined(__AVX512F__)
constexpr int kVector = 16;  // floats per vector register
constexpr int kMaxRows = 12;  // 12 x 2 accumulators of the 32 registers
#elif defined(__AVX__)
constexpr int kVector = 8;
constexpr int kMaxRows = 6;  // 6 x 2 accumulators of the 16 registers
#else
constexpr int kVector = 4;
constexpr int kMaxRows = 6;
#endif
constexpr int kTileChannels = 2 * kVector;  // output channels per tile

typedef float Vec __attribute__((vector_size(kVector * sizeof(float))));

inline Vec Load(const float* p) {
  Vec v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

inline void Store(float* p, Vec v) { std::memcpy(p, &v, sizeof v); }

// dw[r, e] += sum_{j0 <= j < j1} x[(j + x_shift) * c_stride + r] * g[j * d_stride + e] for r < R,
// e < kTileChannels; x, g and dw already point at the tile's first channel.
template <int R>
void AccumulateRow(const float* x, int64_t x_shift, int64_t c_stride, const float* g, int64_t d_stride,
                   int64_t j0, int64_t j1, float* dw) {
  Vec acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = Vec{};
  for (int64_t j = j0; j < j1; ++j) {
    const float* gp = g + j * d_stride;
    const Vec g0 = Load(gp), g1 = Load(gp + kVector);
    const float* xp = x + (j + x_shift) * c_stride;
    for (int r = 0; r < R; ++r) {
      const float xv = xp[r];
      acc[r][0] += xv * g0;
      acc[r][1] += xv * g1;
    }
  }
  for (int r = 0; r < R; ++r) {
    float* out = dw + r * d_stride;
    Store(out, Load(out) + acc[r][0]);
    Store(out + kVector, Load(out + kVector) + acc[r][1]);
  }
}

using RowFn = void (*)(const float*, int64_t, int64_t, const float*, int64_t, int64_t, int64_t, float*);

template <int... Rs>
constexpr std::array<RowFn, sizeof...(Rs)> RowFns(std::integer_sequence<int, Rs...>) {
  return {&AccumulateRow<Rs + 1>...};
}

const auto kRowFns = RowFns(std::make_integer_sequence<int, kMaxRows>{});

struct Tile {
  int64_t p, q, c0, rows, d0;
};

struct Problem {
  const float* x;
  const float* g;
  float* dw;
  int64_t batch, h, w, c, oh, ow, d, kh, kw, top, left;
  std::vector<std::vector<Tile>> chunks;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> finished{0};
};

void RunChunk(const Problem& pr, const std::vector<Tile>& tiles) {
  for (int64_t b = 0; b < pr.batch; ++b) {
    for (int64_t i = 0; i < pr.oh; ++i) {
      const float* g_row = pr.g + (b * pr.oh + i) * pr.ow * pr.d;
      for (const Tile& t : tiles) {
        const int64_t ii = i + t.p - pr.top;
        if (ii < 0 || ii >= pr.h) continue;
        const int64_t shift = t.q - pr.left;
        const int64_t j0 = std::max<int64_t>(0, -shift), j1 = std::min<int64_t>(pr.ow, pr.w - shift);
        if (j0 >= j1) continue;
        const float* x_row = pr.x + (b * pr.h + ii) * pr.w * pr.c + t.c0;
        float* dw = pr.dw + ((t.p * pr.kw + t.q) * pr.c + t.c0) * pr.d + t.d0;
        kRowFns[t.rows - 1](x_row, shift, pr.c, g_row + t.d0, pr.d, j0, j1, dw);
      }
    }
  }
}

// Claims chunks until none is left; every claimed chunk is counted as finished.
void Work(Problem& pr) {
  const int64_t n = static_cast<int64_t>(pr.chunks.size());
  for (int64_t k = pr.next.fetch_add(1); k < n; k = pr.next.fetch_add(1)) {
    RunChunk(pr, pr.chunks[k]);
    pr.finished.fetch_add(1, std::memory_order_release);
  }
}

ffi::Error KernelGradient(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> x, ffi::Buffer<ffi::F32> g,
                          ffi::ResultBuffer<ffi::F32> dw, int64_t top, int64_t left) {
  auto xd = x.dimensions(), gd = g.dimensions(), wd = dw->dimensions();
  if (xd.size() != 4 || gd.size() != 4 || wd.size() != 4 || xd[0] != gd[0] || wd[2] != xd[3] ||
      wd[3] != gd[3]) {
    return ffi::Error::InvalidArgument("conv kernel gradient: x (B,H,W,C), g (B,OH,OW,D), dw (KH,KW,C,D)");
  }
  if (gd[3] % kTileChannels != 0) {
    return ffi::Error::InvalidArgument("conv kernel gradient: output channels must be a multiple of " +
                                       std::to_string(kTileChannels));
  }
  auto pr = std::make_shared<Problem>();
  pr->x = x.typed_data();
  pr->g = g.typed_data();
  pr->dw = dw->typed_data();
  pr->batch = xd[0], pr->h = xd[1], pr->w = xd[2], pr->c = xd[3];
  pr->oh = gd[1], pr->ow = gd[2], pr->d = gd[3];
  pr->kh = wd[0], pr->kw = wd[1], pr->top = top, pr->left = left;
  std::memset(pr->dw, 0, sizeof(float) * pr->kh * pr->kw * pr->c * pr->d);

  std::vector<Tile> tiles;
  for (int64_t p = 0; p < pr->kh; ++p)
    for (int64_t q = 0; q < pr->kw; ++q)
      for (int64_t d0 = 0; d0 < pr->d; d0 += kTileChannels)
        for (int64_t c0 = 0; c0 < pr->c; c0 += kMaxRows)
          tiles.push_back({p, q, c0, std::min<int64_t>(kMaxRows, pr->c - c0), d0});
  const int64_t threads = std::max<int64_t>(1, pool.num_threads());
  const int64_t n_chunks = std::min<int64_t>(static_cast<int64_t>(tiles.size()), threads);
  pr->chunks.resize(n_chunks);
  for (size_t k = 0; k < tiles.size(); ++k) pr->chunks[k * n_chunks / tiles.size()].push_back(tiles[k]);

  // Helpers that start after the work is done find no chunk left and touch nothing else.
  for (int64_t k = 1; k < n_chunks; ++k) pool.Schedule([pr] { Work(*pr); });
  Work(*pr);
  while (pr->finished.load(std::memory_order_acquire) < n_chunks) std::this_thread::yield();
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(IrdepthConvKernelGradient, KernelGradient,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int64_t>("top")
                                  .Attr<int64_t>("left"));

// Output channels per tile: the kernel takes layers whose output channels are a multiple of it.
extern "C" int IrdepthConvTileChannels() { return kTileChannels; }
