// What a thread schedule allows, measured under load: an LD_PRELOAD library (bench only, never
// linked into the core) that wraps libgomp's entry points of every parallel region and times
// each thread's CPU inside the region's body (CLOCK_THREAD_CPUTIME_ID: time stolen by other
// processes and the threads' waits at the region's end do not count).
//
// A program marks sections with miem_probe_section("name") (looked up with dlsym, so it runs
// unchanged without the probe); the probe sums per section, over every call:
//   work     = serial + sum over regions of the CPU of every thread
//   critical = serial + sum over regions of the largest per-thread CPU
//   serial   = the calling thread's CPU in the section outside the regions
//   overhead = the calling thread's CPU in the regions' entry points outside their bodies (the
//              fork, and the join: spinning at the region's end while another thread works)
// work / critical is the speed-up the schedule allows on as many cores as threads (1.0 for a
// serial section); the shortfall of the measured speed-up from it is the machine's (wake-ups,
// memory bandwidth, other processes). miem_probe_result(name, out) gives a section's sums
// (out = regions, serial, work, critical, overhead; seconds) and returns its number of calls.
#include <dlfcn.h>
#include <omp.h>
#include <time.h>

#include <algorithm>
#include <map>
#include <string>

namespace {

double thread_cpu() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

constexpr int kMaxThreads = 256;

struct Call {  // one parallel region's call
  void (*fn)(void*);
  void* data;
  double cpu[kMaxThreads];
};

struct Section {
  long calls = 0, regions = 0;
  double serial = 0.0, work = 0.0, critical = 0.0, overhead = 0.0;
};

std::map<std::string, Section> g_sections;
std::string g_current;
double g_section_start = 0.0;  // the calling thread's CPU at the section's start
double g_in_regions = 0.0;     // the calling thread's CPU inside region calls since then
double g_in_bodies = 0.0;      // ... inside its part of the regions' bodies
long g_regions = 0;
double g_region_max = 0.0, g_region_sum = 0.0;

void body(void* p) {
  Call* c = static_cast<Call*>(p);
  const double t0 = thread_cpu();
  c->fn(c->data);
  c->cpu[omp_get_thread_num() % kMaxThreads] = thread_cpu() - t0;
}

void close_section() {
  if (g_current.empty()) return;
  Section& s = g_sections[g_current];
  const double all = thread_cpu() - g_section_start;
  const double serial = std::max(0.0, all - g_in_regions);
  s.calls += 1;
  s.regions += g_regions;
  s.serial += serial;
  s.work += serial + g_region_sum;
  s.critical += serial + g_region_max;
  s.overhead += std::max(0.0, g_in_regions - g_in_bodies);
}

void open_section(const char* name) {
  g_current = name ? name : "";
  g_regions = 0;
  g_in_regions = g_in_bodies = g_region_max = g_region_sum = 0.0;
  g_section_start = thread_cpu();
}

// Called by the master after the region joined; `all`: its CPU in the whole call.
void account(const Call& c, unsigned team, double all) {
  double mx = 0.0, sum = 0.0;
  for (unsigned t = 0; t < team && t < static_cast<unsigned>(kMaxThreads); ++t) {
    mx = std::max(mx, c.cpu[t]);
    sum += c.cpu[t];
  }
  g_regions += 1;
  g_region_max += mx;
  g_region_sum += sum;
  g_in_bodies += c.cpu[0];
  g_in_regions += all;
}

template <typename F>
F real(const char* name) {
  return reinterpret_cast<F>(dlsym(RTLD_NEXT, name));
}

unsigned team_size(unsigned requested) {
  return requested == 0 ? static_cast<unsigned>(omp_get_max_threads()) : requested;
}

}  // namespace

extern "C" {

void miem_probe_section(const char* name) {
  close_section();
  open_section(name);
}

long miem_probe_result(const char* name, double out[5]) {
  miem_probe_section(nullptr);
  const auto it = g_sections.find(name);
  if (it == g_sections.end()) return 0;
  const Section& s = it->second;
  out[0] = static_cast<double>(s.regions);
  out[1] = s.serial;
  out[2] = s.work;
  out[3] = s.critical;
  out[4] = s.overhead;
  return s.calls;
}

// The region entry points GCC emits: `parallel` and the combined `parallel for` forms.
void GOMP_parallel(void (*fn)(void*), void* data, unsigned n, unsigned flags) {
  static auto f = real<void (*)(void (*)(void*), void*, unsigned, unsigned)>("GOMP_parallel");
  Call c{fn, data, {}};
  const double t0 = thread_cpu();
  f(body, &c, n, flags);
  account(c, team_size(n), thread_cpu() - t0);
}

#define MIEM_PROBE_LOOP(NAME)                                                                   \
  void NAME(void (*fn)(void*), void* data, unsigned n, long start, long end, long incr,         \
            long chunk, unsigned flags) {                                                       \
    static auto f =                                                                             \
        real<void (*)(void (*)(void*), void*, unsigned, long, long, long, long, unsigned)>(    \
            #NAME);                                                                             \
    Call c{fn, data, {}};                                                                       \
    const double t0 = thread_cpu();                                                             \
    f(body, &c, n, start, end, incr, chunk, flags);                                             \
    account(c, team_size(n), thread_cpu() - t0);                                                \
  }
MIEM_PROBE_LOOP(GOMP_parallel_loop_static)
MIEM_PROBE_LOOP(GOMP_parallel_loop_dynamic)
MIEM_PROBE_LOOP(GOMP_parallel_loop_guided)
MIEM_PROBE_LOOP(GOMP_parallel_loop_nonmonotonic_dynamic)
MIEM_PROBE_LOOP(GOMP_parallel_loop_nonmonotonic_guided)
#undef MIEM_PROBE_LOOP

}  // extern "C"
