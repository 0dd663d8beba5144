/*
 * A libmodbus server shaped like the harness's generic profile (corpus/profiles/generic.toml), as a
 * third-party target for `modbus-harness run --profile generic`. Single-threaded.
 *
 *   libmodbus_server tcp [HOST] [PORT]                   Modbus/TCP; PORT 0 (default): any free port
 *   libmodbus_server rtu DEVICE [BAUD] [PARITY] [STOP]   RTU on a serial line or pty (default 19200 N 1)
 *
 * Prints one line once it serves, "listening tcp HOST:PORT" or "listening serial DEVICE", and stops on
 * SIGTERM or SIGINT with exit 0. A signal handler that only sets a flag would never stop it: libmodbus
 * retries its reads on EINTR, so the handler ends the process with _exit (nothing to flush: every output line
 * is flushed when printed).
 *
 * The data model is the generic profile's: 100 coils, 100 discrete inputs, 100 holding and 100 input
 * registers at 0-99 (modbus_mapping_new_start_address), all 0 at start except input register n, which holds
 * n. Modbus/TCP answers any unit id (libmodbus' TCP server does); RTU answers slave address 1 and takes 0 as
 * a broadcast. Every answer is libmodbus' own modbus_reply; TCP connections are served with select() the
 * way libmodbus' examples do (several clients, one at a time), and a connection on which modbus_receive
 * fails is closed as those examples close it.
 *
 * Build: gcc -O2 -Wall libmodbus_server.c -o libmodbus_server $(pkg-config --cflags --libs libmodbus)
 */
#include <arpa/inet.h>
#include <errno.h>
#include <modbus.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

/* Every table of the generic profile holds addresses 0..SIZE-1. */
#define SIZE 100

static void stop(int sig) {
    (void)sig;
    _exit(0);
}

static modbus_mapping_t *generic_map(void) {
    modbus_mapping_t *m = modbus_mapping_new_start_address(0, SIZE, 0, SIZE, 0, SIZE, 0, SIZE);
    if (!m) return NULL;
    for (int i = 0; i < SIZE; i++) m->tab_input_registers[i] = (uint16_t)i;
    return m;
}

static int serve_tcp(const char *host, int port, modbus_mapping_t *map) {
    modbus_t *ctx = modbus_new_tcp(host, port);
    if (!ctx) {
        fprintf(stderr, "error: modbus_new_tcp: %s\n", modbus_strerror(errno));
        return 1;
    }
    /* modbus_tcp_listen binds the context's port: 0 lets the kernel pick one, read back below. */
    int listener = modbus_tcp_listen(ctx, 16);
    if (listener < 0) {
        fprintf(stderr, "error: listen on %s:%d: %s\n", host, port, modbus_strerror(errno));
        return 1;
    }
    struct sockaddr_in bound;
    socklen_t len = sizeof bound;
    if (getsockname(listener, (struct sockaddr *)&bound, &len) < 0) {
        perror("error: getsockname");
        return 1;
    }
    char ip[INET_ADDRSTRLEN];
    inet_ntop(AF_INET, &bound.sin_addr, ip, sizeof ip);
    printf("listening tcp %s:%d\n", ip, ntohs(bound.sin_port));
    fflush(stdout);

    fd_set all;
    FD_ZERO(&all);
    FD_SET(listener, &all);
    int maxfd = listener;
    uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
    for (;;) {
        fd_set ready = all;
        if (select(maxfd + 1, &ready, NULL, NULL, NULL) < 0) {
            if (errno == EINTR) continue;
            perror("error: select");
            return 1;
        }
        for (int fd = 0; fd <= maxfd; fd++) {
            if (!FD_ISSET(fd, &ready)) continue;
            if (fd == listener) {
                int c = accept(listener, NULL, NULL);
                if (c < 0) continue;
                if (c >= FD_SETSIZE) {
                    close(c);
                    continue;
                }
                FD_SET(c, &all);
                if (c > maxfd) maxfd = c;
                continue;
            }
            modbus_set_socket(ctx, fd);
            int rc = modbus_receive(ctx, query);
            if (rc > 0) {
                modbus_reply(ctx, query, rc, map);
            } else if (rc < 0) {
                /* The peer closed, or the request could not be read: drop the connection. */
                close(fd);
                FD_CLR(fd, &all);
            }
        }
    }
}

static int serve_rtu(const char *dev, int baud, char parity, int stop_bits, modbus_mapping_t *map) {
    modbus_t *ctx = modbus_new_rtu(dev, baud, parity, 8, stop_bits);
    if (!ctx) {
        fprintf(stderr, "error: modbus_new_rtu: %s\n", modbus_strerror(errno));
        return 1;
    }
    modbus_set_slave(ctx, 1);
    if (modbus_connect(ctx) < 0) {
        fprintf(stderr, "error: open %s: %s\n", dev, modbus_strerror(errno));
        return 1;
    }
    printf("listening serial %s\n", dev);
    fflush(stdout);
    uint8_t query[MODBUS_RTU_MAX_ADU_LENGTH];
    for (;;) {
        int rc = modbus_receive(ctx, query);
        if (rc > 0) {
            modbus_reply(ctx, query, rc, map);
        } else if (rc < 0) {
            /* A bad frame (CRC, length, timeout inside a frame) is dropped; a line that went away (EOF,
             * EIO: the pty closed) ends the server. */
            if (errno == EBADF || errno == EIO || errno == ENXIO || errno == ECONNRESET) {
                fprintf(stderr, "error: %s: %s\n", dev, modbus_strerror(errno));
                return 1;
            }
        }
        /* rc == 0: a frame for another slave, ignored by libmodbus. */
    }
}

int main(int argc, char **argv) {
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = stop;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    modbus_mapping_t *map = generic_map();
    if (!map) {
        fprintf(stderr, "error: modbus_mapping_new_start_address: %s\n", modbus_strerror(errno));
        return 1;
    }
    if (argc >= 2 && !strcmp(argv[1], "tcp")) {
        const char *host = argc > 2 ? argv[2] : "127.0.0.1";
        int port = argc > 3 ? atoi(argv[3]) : 0;
        return serve_tcp(host, port, map);
    }
    if (argc >= 3 && !strcmp(argv[1], "rtu")) {
        int baud = argc > 3 ? atoi(argv[3]) : 19200;
        char parity = argc > 4 ? argv[4][0] : 'N';
        int stop_bits = argc > 5 ? atoi(argv[5]) : 1;
        if (parity >= 'a') parity -= 'a' - 'A';
        return serve_rtu(argv[2], baud, parity, stop_bits, map);
    }
    fprintf(stderr,
            "usage: %s tcp [HOST] [PORT] | rtu DEVICE [BAUD] [PARITY(N|E|O)] [STOP]\n", argv[0]);
    return 2;
}
