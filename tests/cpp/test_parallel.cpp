// dyq::parallel_for runs every index exactly once, with either backend.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <exception>
#include <mutex>
#include <new>
#include <stdexcept>
#include <thread>
#include <utility>
#include <vector>

#include "parallel/parallel.h"

namespace {

// Counts how often each index of [begin, end) was visited, and records the chunks.
struct Coverage {
  std::vector<std::atomic<int>> visits;
  std::mutex mutex;
  std::vector<std::pair<int64_t, int64_t>> chunks;
  explicit Coverage(int64_t size) : visits(size) {}
};

void run_and_check(int64_t begin, int64_t end, int64_t grain, bool check_grain) {
  Coverage coverage(end);
  dyq::parallel_for(begin, end, grain, [&](int64_t chunk_begin, int64_t chunk_end) {
    {
      std::lock_guard<std::mutex> lock(coverage.mutex);
      coverage.chunks.emplace_back(chunk_begin, chunk_end);
    }
    for (int64_t i = chunk_begin; i < chunk_end; ++i) coverage.visits[i]++;
  });
  for (int64_t i = 0; i < end; ++i) {
    ASSERT_EQ(coverage.visits[i].load(), i >= begin ? 1 : 0) << "index " << i << " grain " << grain;
  }
  for (const auto& [chunk_begin, chunk_end] : coverage.chunks) {
    EXPECT_LT(chunk_begin, chunk_end);
    // The default backend's chunks honour the grain, unless the whole range is smaller than it.
    if (check_grain) EXPECT_GE(chunk_end - chunk_begin, std::min(grain, end - begin));
  }
}

// A host backend: runs the range in chunks of exactly grain_size, last chunk first.
void reversed_chunks_backend(int64_t begin, int64_t end, int64_t grain_size, const dyq::RangeBody& body) {
  const int64_t grain = std::max<int64_t>(grain_size, 1);
  std::vector<int64_t> starts;
  for (int64_t start = begin; start < end; start += grain) starts.push_back(start);
  for (auto it = starts.rbegin(); it != starts.rend(); ++it) body(*it, std::min(*it + grain, end));
}

class ParallelForTest : public ::testing::TestWithParam<bool> {
 protected:
  void SetUp() override { dyq::set_parallel_backend(GetParam() ? reversed_chunks_backend : nullptr); }
  void TearDown() override { dyq::set_parallel_backend(nullptr); }
};

TEST_P(ParallelForTest, CoversEveryIndexExactlyOnce) {
  for (int64_t grain : {1, 3, 64, 1000, 5000}) {
    for (int64_t end : {1, 2, 7, 100, 4097}) run_and_check(0, end, grain, !GetParam());
  }
}

TEST_P(ParallelForTest, CoversAnOffsetRange) { run_and_check(13, 1000, 10, !GetParam()); }

TEST_P(ParallelForTest, EmptyRangeRunsNothing) {
  int calls = 0;
  dyq::parallel_for(5, 5, 1, [&](int64_t, int64_t) { ++calls; });
  dyq::parallel_for(5, 3, 1, [&](int64_t, int64_t) { ++calls; });
  EXPECT_EQ(calls, 0);
}

TEST_P(ParallelForTest, NestedCallsCoverTheirRanges) {
  std::vector<std::atomic<int>> visits(64 * 64);
  dyq::parallel_for(0, 64, 1, [&](int64_t outer_begin, int64_t outer_end) {
    for (int64_t outer = outer_begin; outer < outer_end; ++outer) {
      dyq::parallel_for(0, 64, 4, [&](int64_t inner_begin, int64_t inner_end) {
        for (int64_t inner = inner_begin; inner < inner_end; ++inner) visits[outer * 64 + inner]++;
      });
    }
  });
  for (auto& v : visits) ASSERT_EQ(v.load(), 1);
}

INSTANTIATE_TEST_SUITE_P(Backends, ParallelForTest, ::testing::Values(false, true),
                         [](const auto& info) { return info.param ? "HostBackend" : "ThreadBackend"; });

TEST(ParallelFor, SmallRangeRunsInlineOnTheCallingThread) {
  const auto caller = std::this_thread::get_id();
  std::thread::id runner;
  dyq::parallel_for(0, 10, 100, [&](int64_t, int64_t) { runner = std::this_thread::get_id(); });
  EXPECT_EQ(runner, caller);
}

}  // namespace

namespace {
int one_thread() { return 1; }
int three_threads() { return 3; }
}  // namespace

TEST(ParallelForPool, ThreadCountSourceLimitsTheChunks) {
  dyq::set_parallel_backend(nullptr);
  dyq::set_thread_count_source(one_thread);
  std::atomic<int> calls{0};
  dyq::parallel_for(0, 1000, 1, [&](int64_t, int64_t) { ++calls; });
  EXPECT_EQ(calls.load(), 1);
  dyq::set_thread_count_source(three_threads);
  for (int repeat = 0; repeat < 200; ++repeat) run_and_check(0, 997, 1, true);
  dyq::set_thread_count_source(nullptr);
}

TEST(ParallelForPool, ConcurrentCallersEachCoverTheirRange) {
  dyq::set_parallel_backend(nullptr);
  std::vector<std::thread> callers;
  for (int caller = 0; caller < 4; ++caller) {
    callers.emplace_back([] {
      for (int repeat = 0; repeat < 100; ++repeat) run_and_check(0, 513, 7, true);
    });
  }
  for (auto& caller : callers) caller.join();
}

TEST(ParallelForPool, ExceptionInAWorkerReachesTheCaller) {
  dyq::set_parallel_backend(nullptr);
  for (int repeat = 0; repeat < 50; ++repeat) {
    std::atomic<int> calls{0};
    EXPECT_THROW(dyq::parallel_for(0, 1000, 1,
                                   [&](int64_t begin, int64_t) {
                                     ++calls;
                                     if (begin > 0) throw std::bad_alloc();  // a chunk that is not the first
                                   }),
                 std::bad_alloc);
  }
  // The pool still works afterwards.
  run_and_check(0, 997, 1, true);
}

TEST(ParallelForPool, ExceptionInTheCallersChunkReachesTheCaller) {
  dyq::set_parallel_backend(nullptr);
  EXPECT_THROW(dyq::parallel_for(0, 1000, 1, [](int64_t, int64_t) { throw std::runtime_error("every chunk"); }),
               std::runtime_error);
  run_and_check(0, 997, 1, true);
}

namespace {

std::atomic<int> g_runner_calls{0};
std::atomic<int64_t> g_runner_most_chunks{0};

// A host's chunk runner: one new thread per chunk but the first, which the caller runs; the first
// exception is rethrown once every thread has joined.
void thread_per_chunk_runner(int64_t chunks, const dyq::ChunkTask& task) {
  ++g_runner_calls;
  g_runner_most_chunks = std::max<int64_t>(g_runner_most_chunks.load(), chunks);
  std::mutex error_mutex;
  std::exception_ptr error;
  auto run = [&](int64_t chunk) {
    try {
      task(chunk);
    } catch (...) {
      std::lock_guard<std::mutex> lock(error_mutex);
      if (!error) error = std::current_exception();
    }
  };
  std::vector<std::thread> threads;
  for (int64_t chunk = 1; chunk < chunks; ++chunk) threads.emplace_back(run, chunk);
  run(0);
  for (auto& thread : threads) thread.join();
  if (error) std::rethrow_exception(error);
}

class ParallelForChunkRunner : public ::testing::Test {
 protected:
  void SetUp() override {
    dyq::set_parallel_backend(nullptr);
    dyq::set_thread_count_source(three_threads);
    dyq::set_chunk_runner(thread_per_chunk_runner);
    g_runner_calls = 0;
    g_runner_most_chunks = 0;
  }
  void TearDown() override {
    dyq::set_chunk_runner(nullptr);
    dyq::set_thread_count_source(nullptr);
  }
};

}  // namespace

TEST_F(ParallelForChunkRunner, RunsDyqsChunksOnTheHostsThreads) {
  EXPECT_TRUE(dyq::runs_on_host_threads());
  for (int64_t grain : {1, 3, 64, 1000}) {
    for (int64_t end : {1, 2, 7, 100, 4097}) run_and_check(0, end, grain, true);
  }
  run_and_check(13, 1000, 10, true);
  EXPECT_GT(g_runner_calls.load(), 0);
  EXPECT_EQ(g_runner_most_chunks.load(), 3);  // never more chunks than the thread count source allows
}

TEST_F(ParallelForChunkRunner, NestedCallsRunInlineInTheHostsThreads) {
  std::vector<std::atomic<int>> visits(64 * 64);
  dyq::parallel_for(0, 64, 1, [&](int64_t outer_begin, int64_t outer_end) {
    for (int64_t outer = outer_begin; outer < outer_end; ++outer) {
      const auto thread = std::this_thread::get_id();
      dyq::parallel_for(0, 64, 4, [&](int64_t inner_begin, int64_t inner_end) {
        EXPECT_EQ(std::this_thread::get_id(), thread);
        for (int64_t inner = inner_begin; inner < inner_end; ++inner) visits[outer * 64 + inner]++;
      });
    }
  });
  for (auto& v : visits) ASSERT_EQ(v.load(), 1);
  EXPECT_EQ(g_runner_calls.load(), 1);
}

TEST_F(ParallelForChunkRunner, SerialScopeRunsInlineWithoutTheRunner) {
  const dyq::SerialScope serial(true);
  run_and_check(0, 997, 1, true);
  EXPECT_EQ(g_runner_calls.load(), 0);
}

TEST_F(ParallelForChunkRunner, ExceptionInAChunkReachesTheCaller) {
  EXPECT_THROW(dyq::parallel_for(0, 1000, 1,
                                 [](int64_t begin, int64_t) {
                                   if (begin > 0) throw std::bad_alloc();
                                 }),
               std::bad_alloc);
  run_and_check(0, 997, 1, true);  // and the next call works
}

TEST(ParallelForChunkRunnerOff, NoRunnerMeansDyqsOwnPool) {
  dyq::set_chunk_runner(nullptr);
  EXPECT_FALSE(dyq::runs_on_host_threads());
}
