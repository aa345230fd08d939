import bam.algorithms.Agent;
import bam.algorithms.Algorithm;
import bam.algorithms.BAM;
import bam.algorithms.Dynamics;
import bam.algorithms.ExpertPolicy;
import bam.algorithms.ModelBased;
import bam.algorithms.StateTransition;
import bam.algorithms.TeacherAction;
import bam.algorithms.action.ActionModel;
import bam.algorithms.action.NormalizedActionModel;
import bam.algorithms.optimization.ClippedMomentum;
import bam.algorithms.planning.BoltzmannPlanner;
import bam.algorithms.variational.PointDensity;
import bam.algorithms.variational.Variational;
import bam.domains.Environment;
import bam.domains.NavGrid;
import bam.domains.Task;
import bam.domains.farm_world.FarmWorlds;
import bam.domains.gravity_world.GravityWorlds;
import bam.domains.grid_world.GridWorlds;

import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.Random;
import java.util.function.Supplier;

/**
 * The paper authors' learners timed in their own implementation, as benchmarks/authors.py
 * runs it: BAM and model-based IRL with the settings of their demonstrations experiment
 * (SimulationMain.demonstrationExperiment), fed their expert's goal-terminated demonstrations
 * with the final no-op as their experiment feeds them, and one update (Agent.integrate) timed
 * after every round.
 *
 * Arguments: rounds, repeats (agents per learner), then the environments to run.
 * Output: one line per timed update, "environment learner agent round milliseconds".
 */
public class UpdateTimes {
    /** Our environments' names, and the authors' layouts that are the same grids and tasks. */
    static final Map<String, Supplier<Environment>> ENVIRONMENTS = new LinkedHashMap<>();
    static {
        ENVIRONMENTS.put("wall", () -> GridWorlds.centerWall(NavGrid.FOUR));
        ENVIRONMENTS.put("doorway", GridWorlds::doors);
        ENVIRONMENTS.put("two-rooms", GridWorlds::twoRooms);
        ENVIRONMENTS.put("three-rooms", () -> GridWorlds.threeRooms(NavGrid.FOUR));
        ENVIRONMENTS.put("flip", GravityWorlds::medium_flip);
        ENVIRONMENTS.put("choices", GravityWorlds::choices);
        ENVIRONMENTS.put("two-fields", FarmWorlds::twoFields);
        ENVIRONMENTS.put("three-fields", FarmWorlds::threeFields);
    }

    static Algorithm learner(String name) {
        ActionModel actions = NormalizedActionModel.beta(1.0);
        Variational tasks = PointDensity.builder()
                .optimization(ClippedMomentum.with(0.01, 0.7, 0.1)).build();
        if (name.equals("bam"))
            return BAM.builder().taskSource(tasks)
                    .dynamicsOptimization(ClippedMomentum.with(1.0, 0.7, 0.1))
                    .planningAlgorithm(BoltzmannPlanner.algorithm(1.0)).actionModel(actions)
                    .taskUpdates(20).dynamicsUpdates(20).emUpdates(10).useTransitions(true)
                    .build();
        return ModelBased.builder().taskSource(tasks)
                .dynamicsOptimization(ClippedMomentum.with(1.0, 0.7, 0.1))
                .planningAlgorithm(BoltzmannPlanner.algorithm(1.0)).actionModel(actions)
                .taskUpdates(200).dynamicsUpdates(200).build();
    }

    public static void main(String[] args) {
        int rounds = Integer.parseInt(args[0]);
        int repeats = Integer.parseInt(args[1]);
        List<String> names = List.of(args).subList(2, args.length);
        Random random = new Random(0);
        for (String name : names) {
            Environment environment = ENVIRONMENTS.get(name).get();
            Dynamics dynamics = environment.dynamics();
            Map<String, ExpertPolicy> experts = new LinkedHashMap<>();
            for (Task task : environment.tasks())
                experts.put(task.name(), ExpertPolicy.with(dynamics, task));
            for (String learnerName : List.of("bam", "model-based")) {
                for (int repeat = 0; repeat < repeats; ++repeat) {
                    Agent agent = learner(learnerName).agent(environment.representation());
                    for (int round = 1; round <= rounds; ++round) {
                        for (Task task : environment.tasks()) {
                            ExpertPolicy expert = experts.get(task.name());
                            agent.task(task.name());
                            int state = task.initial(random);
                            for (int step = 0; step < dynamics.depth(); ++step) {
                                int action = expert.action(state, random);
                                agent.observe(TeacherAction.of(state, action));
                                int next = dynamics.transition(state, action, random);
                                agent.observe(StateTransition.of(state, action, next));
                                state = next;
                                if (task.reward(state) > 0.0) {
                                    action = expert.action(state, random);
                                    agent.observe(TeacherAction.of(state, action));
                                    next = dynamics.transition(state, action, random);
                                    agent.observe(StateTransition.of(state, action, next));
                                    break;
                                }
                            }
                        }
                        long started = System.nanoTime();
                        agent.integrate();
                        double milliseconds = (System.nanoTime() - started) / 1e6;
                        System.out.printf("%s %s %d %d %.3f%n", name, learnerName, repeat, round,
                                milliseconds);
                        System.out.flush();
                    }
                }
            }
        }
    }
}
