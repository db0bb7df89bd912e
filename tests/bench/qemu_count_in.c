/* A QEMU TCG plugin (the plugin API of the qemu-user that runs it): counts the guest
 * instructions executed inside one function, its callees included, as callgrind's
 * --toggle-collect does natively, so that the aarch64 build's count sits beside the native one.
 *
 *   qemu-aarch64 -plugin ./libcount_in.so,enter=SYMBOL,leave=SYMBOL -d plugin -D LOG PROGRAM
 *
 * Counting starts each time execution reaches ENTER's first instruction from outside it and
 * stops when it next reaches code of LEAVE (its caller): exact for a function that never runs
 * its caller's code, on one guest thread (kinfly-fuse --threads 1); a branch back to its entry
 * is not another call. Symbols are the ELF symbol table's (mangled)
 * names of the main program. Of those instructions it also counts the Advanced SIMD (NEON) ones,
 * those with a vector register operand (v0.4s, q0), to show whether the 4-lane kernels became
 * NEON. The counts are printed at exit. */
#include <ctype.h>
#include <inttypes.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <qemu-plugin.h>

QEMU_PLUGIN_EXPORT int qemu_plugin_version = QEMU_PLUGIN_VERSION;

/* A block's kind, instruction count and SIMD instruction count, packed into the pointer-sized
 * user data of its callback. */
enum { kOutside = 0, kEnter = 1, kLeave = 2, kKindBits = 2, kCountBits = 31 };
_Static_assert(sizeof(void *) * 8 >= kKindBits + 2 * kCountBits,
               "the counts need 64-bit pointers");

static const char *enter_symbol;
static const char *leave_symbol;
/* ENTER's first instruction: where the first translation block of ENTER starts, since a
 * function is first reached through its entry. */
static uint64_t enter_vaddr;
static bool enter_seen;
static bool inside;
static uint64_t instructions;
static uint64_t simd_instructions;
static uint64_t calls;

static void block_executed(unsigned int vcpu, void *data)
{
    const uint64_t packed = (uintptr_t)data;
    const uint64_t count_mask = (UINT64_C(1) << kCountBits) - 1;
    const unsigned kind = packed & ((1u << kKindBits) - 1);
    (void)vcpu;
    if (kind == kEnter && !inside) {
        inside = true;
        ++calls;
    } else if (kind == kLeave) {
        inside = false;
    }
    if (inside) {
        instructions += (packed >> kKindBits) & count_mask;
        simd_instructions += packed >> (kKindBits + kCountBits);
    }
}

/* An operand that is a whole vector register: vN.<arrangement> or qN. */
static bool has_vector_operand(const char *disassembly)
{
    for (const char *c = disassembly; *c; ++c) {
        if ((*c != 'v' && *c != 'q') || (c != disassembly && isalnum((unsigned char)c[-1])))
            continue;
        const char *d = c + 1;
        if (!isdigit((unsigned char)*d)) continue;
        while (isdigit((unsigned char)*d)) ++d;
        if ((*c == 'v' && *d == '.') || (*c == 'q' && !isalnum((unsigned char)*d))) return true;
    }
    return false;
}

static void block_translated(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    const size_t n = qemu_plugin_tb_n_insns(tb);
    uint64_t simd = 0;
    const char *symbol = qemu_plugin_insn_symbol(qemu_plugin_tb_get_insn(tb, 0));
    const uint64_t vaddr = qemu_plugin_tb_vaddr(tb);
    unsigned kind = kOutside;
    (void)id;
    if (symbol && strcmp(symbol, leave_symbol) == 0) {
        kind = kLeave;
    } else if (symbol && strcmp(symbol, enter_symbol) == 0) {
        if (!enter_seen) {
            enter_seen = true;
            enter_vaddr = vaddr;
        }
        if (vaddr == enter_vaddr) kind = kEnter;
    }
    for (size_t i = 0; i < n; ++i) {
        char *disassembly = qemu_plugin_insn_disas(qemu_plugin_tb_get_insn(tb, i));
        simd += has_vector_operand(disassembly);
        free(disassembly);
    }
    const uint64_t packed = ((simd << kCountBits | n) << kKindBits) | kind;
    qemu_plugin_register_vcpu_tb_exec_cb(tb, block_executed, QEMU_PLUGIN_CB_NO_REGS,
                                         (void *)(uintptr_t)packed);
}

static void at_exit(qemu_plugin_id_t id, void *data)
{
    char line[160];
    (void)id;
    (void)data;
    snprintf(line, sizeof line,
             "count_in: calls %" PRIu64 " instructions %" PRIu64 " simd %" PRIu64 "\n",
             calls, instructions, simd_instructions);
    qemu_plugin_outs(line);
}

QEMU_PLUGIN_EXPORT int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info,
                                           int argc, char **argv)
{
    (void)info;
    for (int i = 0; i < argc; ++i) {
        if (strncmp(argv[i], "enter=", 6) == 0) {
            enter_symbol = argv[i] + 6;
        } else if (strncmp(argv[i], "leave=", 6) == 0) {
            leave_symbol = argv[i] + 6;
        } else {
            fprintf(stderr, "count_in: unknown argument '%s' (enter=SYMBOL,leave=SYMBOL)\n",
                    argv[i]);
            return -1;
        }
    }
    if (!enter_symbol || !leave_symbol) {
        fprintf(stderr, "count_in: needs enter=SYMBOL,leave=SYMBOL\n");
        return -1;
    }
    qemu_plugin_register_vcpu_tb_trans_cb(id, block_translated);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
