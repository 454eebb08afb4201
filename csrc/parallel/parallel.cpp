// dyq::parallel_for: a persistent worker pool by default, replaceable by the host (parallel.h).
#include "parallel/parallel.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <exception>
#include <mutex>
#include <thread>
#include <utility>
#include <vector>

namespace dyq {
namespace {

std::atomic<ParallelForBackend> g_backend{nullptr};
std::atomic<ChunkRunner> g_chunk_runner{nullptr};
std::atomic<ThreadCountSource> g_thread_count{nullptr};

// A body that calls parallel_for again runs its inner range inline instead of oversubscribing.
thread_local bool t_inside_parallel_region = false;
thread_local int t_serial_depth = 0;  // SerialScope

// Marks a host thread as inside dyq's parallel region while it runs a chunk, so that a parallel_for in
// the body runs inline there too.
class InsideParallelRegion {
 public:
  InsideParallelRegion() : was_inside_(std::exchange(t_inside_parallel_region, true)) {}
  ~InsideParallelRegion() { t_inside_parallel_region = was_inside_; }
  InsideParallelRegion(const InsideParallelRegion&) = delete;
  InsideParallelRegion& operator=(const InsideParallelRegion&) = delete;

 private:
  bool was_inside_;
};

// Read once: glibc answers hardware_concurrency by reading sysfs, about 4 us, which every parallel_for
// without a thread count source paid (a 256 x 256 decode took 9.3 us in C++ against 5.7 us through torch).
int hardware_threads() {
  static const int threads = std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  return threads;
}

// Workers started once and woken per call: a decode-sized GEMM takes a fraction of a millisecond, so
// starting threads for every call would cost a noticeable share of it.
class WorkerPool {
 public:
  explicit WorkerPool(int workers) {
    for (int i = 0; i < workers; ++i) threads_.emplace_back([this] { serve(); });
  }

  ~WorkerPool() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stopping_ = true;
      stopping_flag_.store(true, std::memory_order_relaxed);
    }
    wake_.notify_all();
    for (auto& thread : threads_) thread.join();
  }

  int size() const { return static_cast<int>(threads_.size()); }

  // Runs task(c) once for every c in [0, chunks); the caller works too and returns when all are done.
  // An exception thrown by a task (std::bad_alloc in a worker, say) stops the chunks not yet started and
  // is rethrown here, in the calling thread, once every worker has left the job.
  void run(int64_t chunks, const ChunkTask& task) {
    std::lock_guard<std::mutex> one_job_at_a_time(run_mutex_);
    Job job(&task, chunks);
    bool anyone_asleep;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      job_ = &job;
      generation_.fetch_add(1, std::memory_order_release);
      anyone_asleep = sleeping_ > 0;
    }
    if (anyone_asleep) wake_.notify_all();
    drain(job);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      job_ = nullptr;  // late workers no longer join; wait for those that did
    }
    // Watched first, as the workers watch for jobs: sleeping here and being woken took longer than the
    // other thread's share of a small GEMM.
    watch([&] { return job.active.load(std::memory_order_acquire) == 0; });
    std::unique_lock<std::mutex> lock(mutex_);
    done_.wait(lock, [&] { return job.active.load() == 0; });
    if (job.error) std::rethrow_exception(job.error);
  }

 private:
  struct Job {
    Job(const ChunkTask* task_, int64_t chunks_) : task(task_), chunks(chunks_) {}
    const ChunkTask* task;
    int64_t chunks;
    std::atomic<int64_t> next{0};
    std::atomic<int> active{0};  // workers inside drain(); changed under mutex_
    std::mutex error_mutex;
    std::exception_ptr error;  // the first exception a task threw
  };

  static void drain(Job& job) {
    const InsideParallelRegion inside;
    for (int64_t c; (c = job.next.fetch_add(1, std::memory_order_relaxed)) < job.chunks;) {
      try {
        (*job.task)(c);
      } catch (...) {
        std::lock_guard<std::mutex> lock(job.error_mutex);
        if (!job.error) job.error = std::current_exception();
        job.next.store(job.chunks, std::memory_order_relaxed);  // start no further chunk
      }
    }
  }

  void serve() {
    uint64_t seen = 0;
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      lock.unlock();
      await_next_job(seen);
      lock.lock();
      ++sleeping_;
      wake_.wait(lock, [&] { return stopping_ || (job_ != nullptr && generation_.load() != seen); });
      --sleeping_;
      if (stopping_) return;
      seen = generation_.load();
      Job* job = job_;
      ++job->active;
      lock.unlock();
      drain(*job);
      lock.lock();
      if (--job->active == 0) done_.notify_all();
    }
  }

  // A worker that has just finished watches for the next job a short while before it sleeps: a model's
  // forward calls the kernels back to back, and waking a sleeping thread took tens of microseconds
  // (on a virtual machine), more than a small layer's whole GEMM. It yields while it watches, so that
  // another runnable thread (torch's own, another process) gets the core.
  void await_next_job(uint64_t seen) const {
    watch([&] {
      return generation_.load(std::memory_order_acquire) != seen || stopping_flag_.load(std::memory_order_relaxed);
    });
  }

  // Returns once done() holds or kWatchTime has passed, whichever comes first.
  template <typename Done>
  static void watch(Done&& done) {
    const auto deadline = std::chrono::steady_clock::now() + kWatchTime;
    while (!done() && std::chrono::steady_clock::now() < deadline) std::this_thread::yield();
  }

  static constexpr std::chrono::microseconds kWatchTime{200};

  std::vector<std::thread> threads_;
  std::mutex run_mutex_;
  std::mutex mutex_;
  std::condition_variable wake_;
  std::condition_variable done_;
  Job* job_ = nullptr;
  std::atomic<uint64_t> generation_{0};  // written under mutex_, read without it while watching
  int sleeping_ = 0;                     // workers waiting on wake_; guarded by mutex_
  bool stopping_ = false;
  std::atomic<bool> stopping_flag_{false};  // stopping_, for the watch
};

WorkerPool& pool() {
  static WorkerPool instance(hardware_threads() - 1);
  return instance;
}

void chunked_parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body) {
  const int64_t range = end - begin;
  const int64_t grain = std::max<int64_t>(grain_size, 1);
  const ThreadCountSource source = g_thread_count.load(std::memory_order_acquire);
  const ChunkRunner runner = g_chunk_runner.load(std::memory_order_acquire);
  const int64_t threads = std::max(1, source != nullptr ? source() : hardware_threads());
  const int64_t chunks = std::min({threads, range / grain, runner != nullptr ? threads : pool().size() + 1});
  if (chunks <= 1 || t_inside_parallel_region || t_serial_depth > 0) {
    body(begin, end);
    return;
  }
  // Contiguous chunks of nearly equal size, each at least `grain` long.
  const int64_t base = range / chunks;
  const int64_t extra = range % chunks;
  auto chunk_begin = [&](int64_t c) { return begin + c * base + std::min(c, extra); };
  if (runner == nullptr) {
    pool().run(chunks, [&](int64_t c) { body(chunk_begin(c), chunk_begin(c + 1)); });
    return;
  }
  runner(chunks, [&](int64_t c) {
    const InsideParallelRegion inside;
    body(chunk_begin(c), chunk_begin(c + 1));
  });
}

}  // namespace

void parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body) {
  if (end <= begin) return;
  const ParallelForBackend backend = g_backend.load(std::memory_order_acquire);
  if (backend != nullptr) {
    backend(begin, end, grain_size, body);
  } else {
    chunked_parallel_for(begin, end, grain_size, body);
  }
}

SerialScope::SerialScope(bool serial) : serial_(serial) {
  if (serial_) ++t_serial_depth;
}

SerialScope::~SerialScope() {
  if (serial_) --t_serial_depth;
}

void set_parallel_backend(ParallelForBackend backend) { g_backend.store(backend, std::memory_order_release); }

void set_chunk_runner(ChunkRunner runner) { g_chunk_runner.store(runner, std::memory_order_release); }

bool runs_on_host_threads() { return g_chunk_runner.load(std::memory_order_acquire) != nullptr; }

void set_thread_count_source(ThreadCountSource source) { g_thread_count.store(source, std::memory_order_release); }

}  // namespace dyq
