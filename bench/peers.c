/*
 * The C benchmark peers of bench/run.sh: a libmodbus server and client, and a raw TCP ping-pong pair that
 * gives the floor of the loopback (what any request/response protocol of that size costs on this kernel).
 *
 *   peers lm-server tcp PORT              libmodbus Modbus/TCP server on 127.0.0.1 (PORT 0: any free port)
 *   peers lm-server rtu DEVICE BAUD       libmodbus RTU server, slave 1, 8N1
 *   peers lm-client tcp HOST PORT SECS    libmodbus client: FC 03 reads of 2 registers at 0, unit 1
 *   peers lm-client rtu DEVICE BAUD SECS
 *   peers pp-server PORT                  raw TCP: reads 12 bytes, writes 9, TCP_NODELAY
 *   peers pp-client HOST PORT SECS        raw TCP: writes 12 bytes, reads 9, TCP_NODELAY
 *   peers time FILE CMD...                run CMD, write "PEAK_RSS_KIB WALL_SECONDS" to FILE, exit with its
 *                                         status (bench/run.sh's stand-in where /usr/bin/time is not installed)
 *
 * Servers print `listening tcp 127.0.0.1:PORT` (or `listening rtu DEVICE`) once they serve, serve one
 * connection after another until killed (SIGTERM's default action: no handler, see PEERS.md on EINTR), and
 * set TCP_NODELAY on every accepted connection as the simulator does. Clients make one request at a time
 * for SECS seconds after a warm-up of 200 requests and print one line:
 *   RESULT requests=N seconds=S rps=R p50_us=P p99_us=Q
 * Build: gcc -O2 peers.c -o peers $(pkg-config --cflags --libs libmodbus)
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <modbus.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#define WARMUP 200
#define MAX_SAMPLES (1 << 24)

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec / 1e9;
}

static int cmp_u32(const void *a, const void *b) {
    uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
    return x < y ? -1 : x > y;
}

/* Print the result line from per-request latencies in ns. */
static void report(uint32_t *lat, long n, double secs) {
    if (n == 0) {
        printf("RESULT requests=0 seconds=%.3f rps=0 p50_us=0 p99_us=0\n", secs);
        return;
    }
    qsort(lat, n, sizeof *lat, cmp_u32);
    double p50 = lat[(n - 1) * 50 / 100] / 1e3, p99 = lat[(n - 1) * 99 / 100] / 1e3;
    printf("RESULT requests=%ld seconds=%.3f rps=%.0f p50_us=%.1f p99_us=%.1f\n", n, secs, n / secs, p50,
           p99);
    fflush(stdout);
}

static void nodelay(int s) {
    int one = 1;
    setsockopt(s, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
}

static int bound_port(int s) {
    struct sockaddr_in a;
    socklen_t len = sizeof a;
    if (getsockname(s, (struct sockaddr *)&a, &len) < 0) return -1;
    return ntohs(a.sin_port);
}

static int lm_server(int argc, char **argv) {
    modbus_t *ctx;
    int rtu = !strcmp(argv[2], "rtu");
    if (rtu) {
        if (argc < 5) return 2;
        ctx = modbus_new_rtu(argv[3], atoi(argv[4]), 'N', 8, 1);
    } else {
        ctx = modbus_new_tcp("127.0.0.1", atoi(argv[3]));
    }
    if (!ctx) return perror("modbus_new"), 1;
    modbus_mapping_t *map = modbus_mapping_new(0, 0, 100, 0);
    if (!map) return perror("modbus_mapping_new"), 1;
    uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
    if (rtu) {
        modbus_set_slave(ctx, 1);
        if (modbus_connect(ctx) < 0) return fprintf(stderr, "connect: %s\n", modbus_strerror(errno)), 1;
        printf("listening rtu %s\n", argv[3]);
        fflush(stdout);
        for (;;) {
            int rc = modbus_receive(ctx, query);
            if (rc > 0) modbus_reply(ctx, query, rc, map);
        }
    }
    int ls = modbus_tcp_listen(ctx, 4);
    if (ls < 0) return fprintf(stderr, "listen: %s\n", modbus_strerror(errno)), 1;
    printf("listening tcp 127.0.0.1:%d\n", bound_port(ls));
    fflush(stdout);
    for (;;) {
        int s = ls;
        if (modbus_tcp_accept(ctx, &s) < 0) continue;
        nodelay(modbus_get_socket(ctx));
        for (;;) {
            int rc = modbus_receive(ctx, query);
            if (rc > 0)
                modbus_reply(ctx, query, rc, map);
            else if (rc < 0)
                break;
        }
        close(modbus_get_socket(ctx));
    }
}

static int lm_client(int argc, char **argv) {
    modbus_t *ctx;
    double secs;
    if (!strcmp(argv[2], "rtu")) {
        if (argc < 6) return 2;
        ctx = modbus_new_rtu(argv[3], atoi(argv[4]), 'N', 8, 1);
        secs = atof(argv[5]);
    } else {
        if (argc < 6) return 2;
        ctx = modbus_new_tcp(argv[3], atoi(argv[4]));
        secs = atof(argv[5]);
    }
    if (!ctx) return perror("modbus_new"), 1;
    modbus_set_slave(ctx, 1);
    modbus_set_response_timeout(ctx, 1, 0);
    if (modbus_connect(ctx) < 0) return fprintf(stderr, "connect: %s\n", modbus_strerror(errno)), 1;
    uint16_t regs[2];
    for (int i = 0; i < WARMUP; i++)
        if (modbus_read_registers(ctx, 0, 2, regs) != 2)
            return fprintf(stderr, "read: %s\n", modbus_strerror(errno)), 1;
    uint32_t *lat = malloc(sizeof *lat * MAX_SAMPLES);
    long n = 0;
    double start = now_s(), end = start + secs, t = start;
    while (t < end && n < MAX_SAMPLES) {
        if (modbus_read_registers(ctx, 0, 2, regs) != 2)
            return fprintf(stderr, "read: %s\n", modbus_strerror(errno)), 1;
        double t2 = now_s();
        lat[n++] = (uint32_t)((t2 - t) * 1e9);
        t = t2;
    }
    report(lat, n, t - start);
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}

/* Read exactly n bytes; 0 on EOF or error. */
static int read_full(int s, uint8_t *buf, int n) {
    int got = 0;
    while (got < n) {
        ssize_t r = read(s, buf + got, n - got);
        if (r <= 0) {
            if (r < 0 && errno == EINTR) continue;
            return 0;
        }
        got += (int)r;
    }
    return 1;
}

static int pp_server(char **argv) {
    int ls = socket(AF_INET, SOCK_STREAM, 0), one = 1;
    setsockopt(ls, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons(atoi(argv[2]))};
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (bind(ls, (struct sockaddr *)&a, sizeof a) < 0 || listen(ls, 4) < 0) return perror("listen"), 1;
    printf("listening tcp 127.0.0.1:%d\n", bound_port(ls));
    fflush(stdout);
    /* An FC 03 answer of 2 registers: MBAP (7) + FC + byte count = 9 bytes before the data. */
    uint8_t req[12], rsp[9] = {0, 1, 0, 0, 0, 3, 1, 3, 0};
    for (;;) {
        int s = accept(ls, NULL, NULL);
        if (s < 0) continue;
        nodelay(s);
        while (read_full(s, req, sizeof req))
            if (write(s, rsp, sizeof rsp) != sizeof rsp) break;
        close(s);
    }
}

static int pp_client(char **argv) {
    int s = socket(AF_INET, SOCK_STREAM, 0);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons(atoi(argv[3]))};
    inet_pton(AF_INET, argv[2], &a.sin_addr);
    if (connect(s, (struct sockaddr *)&a, sizeof a) < 0) return perror("connect"), 1;
    nodelay(s);
    double secs = atof(argv[4]);
    uint8_t req[12] = {0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 2}, rsp[9];
    for (int i = 0; i < WARMUP; i++)
        if (write(s, req, sizeof req) != sizeof req || !read_full(s, rsp, sizeof rsp)) return 1;
    uint32_t *lat = malloc(sizeof *lat * MAX_SAMPLES);
    long n = 0;
    double start = now_s(), end = start + secs, t = start;
    while (t < end && n < MAX_SAMPLES) {
        if (write(s, req, sizeof req) != sizeof req || !read_full(s, rsp, sizeof rsp))
            return fprintf(stderr, "ping-pong: connection lost\n"), 1;
        double t2 = now_s();
        lat[n++] = (uint32_t)((t2 - t) * 1e9);
        t = t2;
    }
    report(lat, n, t - start);
    close(s);
    return 0;
}

/* Peak RSS of CMD itself: this process is small, so what the child had before exec does not count. */
static int timed(char **argv) {
    double t = now_s();
    pid_t pid = fork();
    if (pid < 0) return perror("fork"), 1;
    if (pid == 0) {
        execvp(argv[3], argv + 3);
        perror("exec");
        _exit(127);
    }
    int status = 0;
    struct rusage ru;
    if (wait4(pid, &status, 0, &ru) < 0) return perror("wait4"), 1;
    FILE *f = fopen(argv[2], "w");
    if (!f) return perror(argv[2]), 1;
    fprintf(f, "%ld %.2f\n", ru.ru_maxrss, now_s() - t);
    fclose(f);
    return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

int main(int argc, char **argv) {
    if (argc >= 4 && !strcmp(argv[1], "lm-server")) return lm_server(argc, argv);
    if (argc >= 6 && !strcmp(argv[1], "lm-client")) return lm_client(argc, argv);
    if (argc >= 3 && !strcmp(argv[1], "pp-server")) return pp_server(argv);
    if (argc >= 5 && !strcmp(argv[1], "pp-client")) return pp_client(argv);
    if (argc >= 4 && !strcmp(argv[1], "time")) return timed(argv);
    fprintf(stderr, "usage: see the comment at the top of bench/peers.c\n");
    return 2;
}
