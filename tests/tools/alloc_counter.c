/* Counts heap allocations per thread in an unmodified program, for the steady-state test of
 * kinfly-fw (tests/firmware/test_firmware_faults.py): LD_PRELOAD=libkinfly_alloc_counter.so.
 * Every malloc-family call adds one to a thread-local count; when a thread ends (and at exit for
 * the main thread) one line "<thread name> <count>" is appended to $KINFLY_ALLOC_REPORT. Threads
 * are told apart by the names kinfly-fw gives them (pthread_setname_np), read at their end.
 * glibc's __libc_* entry points are called directly, so there is no dlsym and no recursion. */
#define _GNU_SOURCE
#include <fcntl.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

extern void* __libc_malloc(size_t size);
extern void* __libc_calloc(size_t n, size_t size);
extern void* __libc_realloc(void* p, size_t size);
extern void* __libc_memalign(size_t alignment, size_t size);
extern void __libc_free(void* p);

static __thread long long t_count;
static __thread int t_registered;
static pthread_key_t g_key;
static pthread_once_t g_once = PTHREAD_ONCE_INIT;

static void report(long long count) {
  const char* path = getenv("KINFLY_ALLOC_REPORT");
  if (path == NULL) return;
  char name[32] = "?";
  pthread_getname_np(pthread_self(), name, sizeof name);
  char line[80];
  const int n = snprintf(line, sizeof line, "%s %lld\n", name, count);
  const int fd = open(path, O_WRONLY | O_CREAT | O_APPEND, 0644);
  if (fd < 0) return;
  if (write(fd, line, (size_t)n) != n) { /* nothing better to do in a dying thread */ }
  close(fd);
}

static void on_thread_exit(void* unused) {
  (void)unused;
  report(t_count);
}

static void make_key(void) { pthread_key_create(&g_key, on_thread_exit); }

static void count_one(void) {
  ++t_count;
  if (!t_registered) {
    t_registered = 1;
    /* The key's destructor runs only for threads that set a value. */
    pthread_once(&g_once, make_key);
    pthread_setspecific(g_key, &t_registered);
  }
}

__attribute__((destructor)) static void on_exit_main(void) {
  if (getpid() == gettid()) report(t_count);
}

void* malloc(size_t size) { count_one(); return __libc_malloc(size); }
void* calloc(size_t n, size_t size) { count_one(); return __libc_calloc(n, size); }
void* realloc(void* p, size_t size) { count_one(); return __libc_realloc(p, size); }
void free(void* p) { __libc_free(p); }
void* memalign(size_t alignment, size_t size) { count_one(); return __libc_memalign(alignment, size); }
void* aligned_alloc(size_t alignment, size_t size) { count_one(); return __libc_memalign(alignment, size); }
int posix_memalign(void** out, size_t alignment, size_t size) {
  count_one();
  void* p = __libc_memalign(alignment, size);
  if (p == NULL) return 12; /* ENOMEM */
  *out = p;
  return 0;
}
